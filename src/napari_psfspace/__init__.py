"""napari-psfspace: learn space-varying PSF operators from images of micro-beads.

The public API is headless (numpy / scipy / scikit-image); the napari widgets sit on
top of it. Typical use::

    import napari_psfspace as ps

    image, truth = ps.simulate_beads((1024, 1024), n_beads=150, seed=0)
    op = ps.estimate_operator(image, psf_radius=truth.psf_radius)
    psf = op.psf_at(100.0, 900.0)        # PSF at row 100, column 900, sums to 1
    blurred = op.apply(image.astype("float32"))
    op.save("model.npz")
    op = ps.load_operator("model.npz")
"""

__version__ = "0.1.0"

from .core.beads.detect import Beads, NoBeadsError, detect_beads, suggest_psf_radius
from .core.beads.focus import best_focus_index
from .core.beads.patches import Patches, extract_patches
from .core.beads.scale import spot_scale
from .core.common.errors import PsfSpaceError
from .core.diagnosis.loop import Diagnosis, diagnose
from .core.model.estimate import Estimation, Progress, estimate_operator, iter_estimate
from .core.model.operator import ProductConvolution, load_operator
from .core.simulation import FieldAberrations, Optics, SimulationTruth, simulate_beads, simulate_psf
from .core.simulation.metrics import psf_error

__all__ = [
    "Beads",
    "Diagnosis",
    "Estimation",
    "FieldAberrations",
    "NoBeadsError",
    "Optics",
    "Patches",
    "ProductConvolution",
    "Progress",
    "PsfSpaceError",
    "SimulationTruth",
    "__version__",
    "best_focus_index",
    "detect_beads",
    "diagnose",
    "estimate_operator",
    "extract_patches",
    "iter_estimate",
    "load_operator",
    "psf_error",
    "simulate_beads",
    "simulate_psf",
    "spot_scale",
    "suggest_psf_radius",
]
