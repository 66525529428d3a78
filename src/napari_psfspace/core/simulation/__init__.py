"""Beside the flow: the bead-image simulator, its known truth, and the scene set.

Gives synthetic bead images with their ground truth for tests and benches: optics and
field aberrations, the bead scene, the camera and the effects a real image holds
(:mod:`.optics`, :mod:`.aberrations`, :mod:`.scene`, :mod:`.render`, :mod:`.camera`,
:mod:`.effects`, :mod:`.truth`), Zernike polynomials (:mod:`.zernike`), seeded random
scenes over a set of settings (:mod:`.scene_set`) and errors against the truth (:mod:`.metrics`).
Nothing in it is needed to process a measured image, and no stage imports it; it may
import ``beads`` (a bead's size) and ``common``.

The names below are those the single ``core/simulate.py`` of earlier versions gave.
"""

from ..beads.sphere import sphere_transfer
from .aberrations import FieldAberrations
from .effects import EFFECTS
from .optics import Optics, simulate_psf
from .scene import simulate_beads
from .truth import SimulationTruth

__all__ = [
    "EFFECTS",
    "FieldAberrations",
    "Optics",
    "SimulationTruth",
    "simulate_beads",
    "simulate_psf",
    "sphere_transfer",
]
