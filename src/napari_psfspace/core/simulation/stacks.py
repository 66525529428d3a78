"""Stacks of bead images of one microscope under hidden conditions.

A microscope is not one operator: focus, tilts and temperature change its blur. A stack
is ``K`` images of the same optics, each under its own *condition* drawn at random and
not told to the estimator:

- a focus shift: defocus (Zernike 4) constant over the field;
- a tilt of the slide: defocus growing linearly across the field;
- a temperature-like drift of the spherical aberration (Zernike 11).

Each condition is added to a base aberration field (a preset), so that the images share
the microscope's own field-dependent astigmatism and coma. Every image comes with its
:class:`~.truth.SimulationTruth`, i.e. its true operator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .aberrations import PRESETS, FieldAberrations
from .optics import Optics
from .scene import simulate_beads
from .truth import SimulationTruth

#: Default spread of the hidden conditions (waves rms): focus shift (uniform, +-),
#: tilt (defocus per unit of field coordinate, normal sd), spherical drift (uniform, +-).
CONDITIONS = {"focus": 0.12, "tilt": 0.05, "spherical": 0.04}


@dataclass(frozen=True)
class Condition:
    """The hidden state of the microscope for one image (waves rms)."""

    focus: float
    tilt_u: float
    tilt_v: float
    spherical: float

    def aberrations(self, base: FieldAberrations) -> FieldAberrations:
        """``base`` with this condition's defocus, tilt and spherical terms added."""
        terms = {j: list(c) + [0.0] * (6 - len(c)) for j, c in base.terms.items()}
        d = terms.setdefault(4, [0.0] * 6)
        d[0] += self.focus
        d[1] += self.tilt_u
        d[2] += self.tilt_v
        terms.setdefault(11, [0.0] * 6)[0] += self.spherical
        return FieldAberrations({j: tuple(c) for j, c in terms.items()})


def random_conditions(k: int, seed: int | np.random.Generator | None = 0,
                      spread: dict | None = None) -> list[Condition]:
    """``k`` conditions drawn with the spreads of :data:`CONDITIONS` (or ``spread``)."""
    s = {**CONDITIONS, **(spread or {})}
    rng = np.random.default_rng(seed)
    return [Condition(float(rng.uniform(-s["focus"], s["focus"])),
                      float(rng.normal(0.0, s["tilt"])), float(rng.normal(0.0, s["tilt"])),
                      float(rng.uniform(-s["spherical"], s["spherical"])))
            for _ in range(int(k))]


def within(conditions: list[Condition], reference: list[Condition]) -> np.ndarray:
    """Which ``conditions`` lie inside the range of ``reference`` on every parameter (a
    family learnt from ``reference`` interpolates them rather than extrapolates)."""
    ref = np.array([[c.focus, c.tilt_u, c.tilt_v, c.spherical] for c in reference])
    got = np.array([[c.focus, c.tilt_u, c.tilt_v, c.spherical] for c in conditions])
    return np.all((got >= ref.min(axis=0)) & (got <= ref.max(axis=0)), axis=1)


def simulate_stack(
    k: int = 10,
    shape: tuple[int, int] = (512, 512),
    n_beads: int = 40,
    *,
    base: str | FieldAberrations = "moderate",
    optics: Optics | None = None,
    conditions: list[Condition] | None = None,
    seed: int = 0,
    **kwargs,
) -> tuple[list[np.ndarray], list[SimulationTruth], list[Condition]]:
    """``k`` bead images of one microscope, each under its own hidden condition.

    Parameters
    ----------
    k : int
        Number of images (conditions).
    shape : tuple of int
        ``(H, W)`` of every image, pixels.
    n_beads : int
        Beads per image (each image has its own bead layout); 5-8 gives the few-beads
        stacks where one image alone supports only one PSF.
    base : str or FieldAberrations
        The microscope's own aberration field (a preset name or a field).
    optics : Optics, optional
        Shared by every image; default :class:`~.optics.Optics()` (NA 1.3, 600 nm,
        65 nm pixels).
    conditions : list of Condition, optional
        Default: :func:`random_conditions` ``(k, seed)``.
    seed : int
        Seeds the conditions and each image (image ``i`` uses ``[seed, i]``).
    **kwargs
        Passed to :func:`~.scene.simulate_beads` (amplitude, background, ...).

    Returns
    -------
    images : list of ndarray, each of shape (H, W)
    truths : list of SimulationTruth
    conditions : list of Condition
    """
    if int(k) < 1:
        raise ValueError(f"`k` must be a positive number of images, got {k!r}")
    base_field = FieldAberrations(PRESETS[base]) if isinstance(base, str) else base
    conds = random_conditions(k, [seed, 1]) if conditions is None else list(conditions)
    if len(conds) != int(k):
        raise ValueError(f"`conditions` must hold k={k} conditions, got {len(conds)}")
    images, truths = [], []
    for i, c in enumerate(conds):
        image, truth = simulate_beads(shape, n_beads, aberrations=c.aberrations(base_field),
                                      optics=optics, seed=np.random.default_rng([seed, i]),
                                      **kwargs)
        images.append(image)
        truths.append(truth)
    return images, truths, conds
