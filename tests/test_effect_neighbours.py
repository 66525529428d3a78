"""Neighbours (core/effects/neighbours.py): a companion merged with its bead (1-3 px away,
inside the core) is located by a joint two-source fit of the bead's patch, so that it can
be fitted jointly instead of the bead being set aside."""

import numpy as np
import pytest

from napari_psfspace.core.diagnosis.effects.neighbours import locate_companion
from napari_psfspace.core.diagnosis.residuals import BeadResiduals, fourier_shift
from napari_psfspace.core.simulation import Optics, simulate_psf


def _bead(offset, ratio, seed, photons=2e4, background=50.0):
    """A bead at the patch centre with a companion at ``offset`` (px), Poisson noise."""
    h = simulate_psf(optics=Optics(pixel_size=0.1), size=31)
    h /= h.sum()
    comp = fourier_shift(h[None], np.array([offset], float))[0]
    mean = photons * (h + ratio * comp) + background
    rng = np.random.default_rng(seed)
    data = rng.poisson(np.clip(mean, 0, None)).astype(float)
    yy, xx = np.mgrid[-15:16, -15:16]
    mask = np.hypot(yy, xx) <= 12
    # the single-source fit the residual analysis made: the model PSF at the bead
    amp = photons * (1 + ratio)
    return BeadResiduals(
        positions=np.array([[100.0, 100.0]]), amplitude=np.array([amp]),
        background=np.array([background]), data=data[None],
        model=(amp * h + background)[None], variance=np.clip(mean, 1, None)[None],
        fit_mask=mask[None], rel_energy=np.zeros(1), chi2=np.zeros(1), dof=np.ones(1),
        floor=np.zeros(1))


@pytest.mark.parametrize("offset, ratio", [((1.5, -1.0), 0.7), ((0.0, 2.5), 1.0),
                                           ((-2.0, 0.5), 0.5), ((1.13, 0.77), 0.6)])
@pytest.mark.parametrize("seed", [0, 1])
def test_a_merged_companion_is_located(offset, ratio, seed):
    q = locate_companion(_bead(offset, ratio, seed), 0)
    assert q is not None
    # measured: within 0.04 px of the truth for all eight (0.25 px grid, refined to 0.05)
    assert np.hypot(q[0] - offset[0], q[1] - offset[1]) <= 0.15

