"""Stage 4, subspace (issue 11): a family of operators from many bead images.

Takes images of one microscope under varying conditions (a list, a stack's slices, or
loaders that read one image at a time); gives an :class:`~.result.OperatorSubspace`: a
PSF basis ``h_i``, a basis of spatial variations ``a_j`` on the coarse grid, one small
matrix ``Gamma_k`` per image, and the cone of the ``Gamma_k`` (paper, sections 2.4-2.5).
The per-image work runs as dask tasks (:mod:`.estimate`, :mod:`.patches`); the result's
file format is in :mod:`.subspace_file`. Imports ``model``, ``beads`` and ``common``.
"""

from .estimate import estimate_subspace, iter_estimate_subspace
from .result import OperatorSubspace

__all__ = ["OperatorSubspace", "estimate_subspace", "iter_estimate_subspace"]
