"""``python -m napari_psfspace.cli``: the ``psfspace`` command."""

import sys

from . import main

sys.exit(main())
