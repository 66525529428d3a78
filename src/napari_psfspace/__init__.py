"""napari-psfspace: learn space-varying PSF operators from images of micro-beads.

The public API is headless (numpy / scipy / scikit-image); the napari widgets sit on
top of it. Every long computation ``NAME`` has a generator twin ``iter_NAME`` that
yields :class:`Progress` records and returns the same result (for a GUI that shows
progress and can stop). Typical use::

    import napari_psfspace as ps

    image, truth = ps.simulate_beads((1024, 1024), n_beads=150, seed=0)
    op = ps.estimate_operator(image, psf_radius=truth.psf_radius)
    psf = op.psf_at(100.0, 900.0)        # PSF at row 100, column 900, sums to 1
    blurred = op.apply(image.astype("float32"))
    op.save("model.npz")
    op = ps.load_operator("model.npz")

One operator (:func:`estimate_operator`), its diagnosis (:func:`diagnose`), a family
of operators from many images (:func:`estimate_family`, :func:`load_family`), the
operator of the family that explains a few beads (:func:`identify_operator`) and the
deblurring with it (:func:`deblur`); from a bead z-stack, a space-varying 3D PSF
(:func:`estimate_operator_3d`).
"""

from .core.common.version import package_version

__version__ = package_version()

from .core.beads.detect import Beads, NoBeadsError, detect_beads
from .core.beads.focus import best_focus_index
from .core.beads.patches import Patches, extract_patches
from .core.beads.radius import suggest_psf_radius
from .core.beads.scale import spot_scale
from .core.common.errors import PsfSpaceError
from .core.common.progress import Progress, run_with_progress
from .core.diagnosis.loop import Diagnosis, diagnose, iter_diagnose, iter_heldout_error
from .core.family import OperatorFamily, estimate_family, iter_estimate_family
from .core.family.result import load_family
from .core.model.estimate import Estimation, estimate_operator, iter_estimate
from .core.model.operator import ProductConvolution, load_operator
from .core.restore import Deblurred, deblur, identify_operator, iter_deblur
from .core.simulation import FieldAberrations, Optics, SimulationTruth, simulate_beads, simulate_psf
from .core.simulation.focus import simulate_focus_series
from .core.simulation.metrics import psf_error
from .core.volume import (
    ProductConvolution3D,
    deblur_3d,
    estimate_operator_3d,
    iter_deblur_3d,
    iter_estimate_operator_3d,
    iter_richardson_lucy_3d,
    load_operator_3d,
    richardson_lucy_3d,
    richardson_lucy_3d_exchange,
    richardson_lucy_3d_tiled,
)

__all__ = [
    "Beads",
    "Deblurred",
    "Diagnosis",
    "Estimation",
    "FieldAberrations",
    "NoBeadsError",
    "OperatorFamily",
    "Optics",
    "Patches",
    "ProductConvolution",
    "ProductConvolution3D",
    "Progress",
    "PsfSpaceError",
    "SimulationTruth",
    "__version__",
    "best_focus_index",
    "deblur",
    "deblur_3d",
    "detect_beads",
    "diagnose",
    "estimate_operator",
    "estimate_operator_3d",
    "estimate_family",
    "extract_patches",
    "identify_operator",
    "iter_deblur",
    "iter_deblur_3d",
    "iter_diagnose",
    "iter_estimate",
    "iter_estimate_operator_3d",
    "iter_estimate_family",
    "iter_heldout_error",
    "iter_richardson_lucy_3d",
    "load_operator",
    "load_operator_3d",
    "load_family",
    "psf_error",
    "richardson_lucy_3d",
    "richardson_lucy_3d_exchange",
    "richardson_lucy_3d_tiled",
    "run_with_progress",
    "simulate_beads",
    "simulate_focus_series",
    "simulate_psf",
    "spot_scale",
    "suggest_psf_radius",
]


def __getattr__(name: str):
    """The old names of the family of operators ("subspace"): deprecated, still there."""
    from .core.common.deprecate import module_getattr

    return module_getattr(__name__, {
        "OperatorSubspace": ("OperatorFamily", lambda: OperatorFamily),
        "estimate_subspace": ("estimate_family", lambda: estimate_family),
        "iter_estimate_subspace": ("iter_estimate_family", lambda: iter_estimate_family),
        "load_subspace": ("load_family", lambda: load_family)})(name)
