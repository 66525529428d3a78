"""Deprecated: the family stage's name until version 0.2.0, now
:mod:`napari_psfspace.core.family`. Importing it, or any of its modules (``result``,
``estimate``, ...), gives the new module, with a FutureWarning."""

import importlib
import sys

from ..common.deprecate import warn

_MODULES = ("choice", "estimate", "patches", "result", "shrink", "sizes")

warn("napari_psfspace.core.subspace", "napari_psfspace.core.family", stacklevel=2)
for _name in _MODULES:
    sys.modules[f"{__name__}.{_name}"] = importlib.import_module(f"..family.{_name}",
                                                                 __package__)
sys.modules[f"{__name__}.subspace_file"] = importlib.import_module("..family.family_file",
                                                                   __package__)
sys.modules[__name__] = importlib.import_module("..family", __package__)
