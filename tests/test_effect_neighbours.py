"""Neighbours (core/effects/neighbours.py): a companion merged with its bead (1-3 px away,
inside the core) is located by a joint two-source fit of the bead's patch, so that it can
be fitted jointly instead of the bead being set aside."""

import numpy as np
import pytest

from napari_psfspace import simulate_beads
from napari_psfspace.core.diagnosis.effects.neighbours import locate_companion
from napari_psfspace.core.diagnosis.loop import diagnose
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
    pair = locate_companion(_bead(offset, ratio, seed), 0)
    assert pair is not None
    (sy, sx), (qy, qx) = pair
    # the bead where it was put, the companion at its offset: within a few noise-limited
    # hundredths of a pixel (0.15 px: 3x the 0.05 px the grid alone reached)
    assert np.hypot(sy, sx) <= 0.15
    assert np.hypot(sy + qy - offset[0], sx + qx - offset[1]) <= 0.15


@pytest.mark.parametrize("offset, ratio", [((1.5, -1.0), 0.7), ((0.0, 2.5), 1.0),
                                           ((-2.0, 0.5), 0.5)])
def test_a_pair_centred_by_the_detector_is_put_back(offset, ratio):
    """The detector centres a merged pair at its brightness centroid: the bead is taken
    there, and the joint fit moves it back to where it lies."""
    offset = np.asarray(offset, float)
    centroid = ratio / (1 + ratio) * offset  # from the bead, px
    res = _bead(offset, ratio, 3)
    h = (res.model[0] - res.background[0]) / res.amplitude[0]
    moved = fourier_shift(h[None], centroid[None])[0]  # the single fit at the centroid
    res.model[0] = res.amplitude[0] * moved + res.background[0]
    res.positions[0] += centroid
    pair = locate_companion(res, 0)
    assert pair is not None
    shift, q = np.asarray(pair[0]), np.asarray(pair[1])
    # from the centroid back to the two beads (which one is "the bead" of an equal
    # pair is arbitrary: the two positions as a set)
    found = np.array([centroid + shift, centroid + shift + q])
    truth = np.array([[0.0, 0.0], offset])
    err = min(np.hypot(*(found - truth).T).max(), np.hypot(*(found[::-1] - truth).T).max())
    assert err <= 0.15



@pytest.mark.parametrize("seed", [0, 1])
def test_pairs_inside_the_core_are_round_once_fitted_jointly(seed):
    """A fifth of the beads with a companion 1-3 px away: the stretched beads are fitted
    as pairs, and the elongation test, which found them, finds (almost) none after."""
    image, truth = simulate_beads((640, 640), 80, aberrations="moderate", seed=seed,
                                  effects={"neighbours": {"fraction": 0.2,
                                                          "distance_px": (1.0, 3.0),
                                                          "amplitude": (0.5, 1.0)}})
    d = diagnose(image, psf_radius=truth.psf_radius, effects=["neighbours"])
    step = next(s for s in d.steps if s.effect == "neighbours")
    assert step.accepted and step.statistic["test"] == "elongated_beads"
    # measured (seeds 0-2): 6-9 beads flagged before, 0-1 after; with the bead held
    # where the detector centred the pair (the previous fit), 5 and 4 stayed flagged on
    # seeds 0 and 1 and the error fell 12-18 %
    assert step.statistic["significant_before"] and step.statistic["significant_after"] is False
    assert step.error_after < 0.75 * step.error_before  # measured 0.51-0.59 of it
