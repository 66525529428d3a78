"""Stage 4, family: a family of operators from many bead images.

Takes images of one microscope under varying conditions (a list, a stack's slices, or
loaders that read one image at a time); gives an :class:`~.result.OperatorFamily`: a
PSF basis ``h_i``, a basis of spatial variations ``a_j`` on the coarse grid, one small
matrix ``Gamma_k`` per image, and the cone of the ``Gamma_k`` (paper, sections 2.4-2.5).
The per-image work runs as dask tasks (:mod:`.estimate`, :mod:`.patches`); the result's
file format is in :mod:`.family_file`. Imports ``model``, ``beads`` and ``common``.
"""

from .estimate import estimate_family, iter_estimate_family
from .result import OperatorFamily

__all__ = ["OperatorFamily", "estimate_family", "iter_estimate_family"]


def _aliases():
    from . import result

    return {"OperatorSubspace": ("OperatorFamily", lambda: OperatorFamily),
            "estimate_subspace": ("estimate_family", lambda: estimate_family),
            "iter_estimate_subspace": ("iter_estimate_family", lambda: iter_estimate_family),
            "load_subspace": ("load_family", lambda: result.load_family),
            "save_subspace": ("save_family", lambda: result.save_family)}


def __getattr__(name: str):
    """The stage's old names (before "family" was its one name): deprecated."""
    from ..common.deprecate import module_getattr

    return module_getattr(__name__, _aliases())(name)
