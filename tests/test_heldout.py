"""Tests of held-out beads (core/heldout.py)."""

import numpy as np
import pytest

from napari_psfspace.core.beads.patches import extract_patches, patch_size
from napari_psfspace.core.model.heldout import HeldoutResiduals, heldout_residuals, split_holdout
from napari_psfspace.core.model.operator import ProductConvolution
from synthetic import integrated_gaussian

SHAPE = (256, 256)
SIGMA = 1.5  # PSF standard deviation, pixels
R = 6.0  # psf_radius: patch size 17
NOISE = 1.0


def _uniform_positions(seed, n=200, shape=(512, 512)):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 1, (n, 2)) * (np.array(shape) - 1)


@pytest.mark.parametrize("fraction", [0.1, 0.2, 0.3, 0.5])
@pytest.mark.parametrize("n", [57, 200])
def test_split_fraction(fraction, n):
    pos = _uniform_positions(0, n)
    mask = split_holdout(pos, (512, 512), fraction)
    assert mask.dtype == bool and mask.shape == (n,)
    assert abs(mask.sum() - fraction * n) <= 1


def test_split_spread_over_field():
    pos = _uniform_positions(1, 200)
    mask = split_holdout(pos, (512, 512), 0.2)
    quad = (pos[:, 0] >= 256).astype(int) * 2 + (pos[:, 1] >= 256)
    counts = np.bincount(quad[mask], minlength=4)
    # about 10 per quadrant: measured [11 11 9 9] on seed 1
    assert counts.min() >= 5
    # finer: on a 4 x 4 grid of cells every cell gets one and none more than 6 of the
    # 40 (measured 1-4). A random 20 % draw would leave ~1.3 cells empty on average.
    cell = (pos[mask] // 128).astype(int)
    per_cell = np.bincount(cell[:, 0] * 4 + cell[:, 1], minlength=16)
    assert per_cell.min() >= 1 and per_cell.max() <= 6


def test_split_deterministic():
    pos = _uniform_positions(2, 150)
    a = split_holdout(pos, (512, 512), 0.25)
    b = split_holdout(pos.copy(), (512, 512), 0.25)
    assert np.array_equal(a, b)
    # order-independent: permuting the beads permutes the mask
    perm = np.random.default_rng(3).permutation(len(pos))
    assert np.array_equal(split_holdout(pos[perm], (512, 512), 0.25), a[perm])


@pytest.mark.parametrize("fraction", [0.0, -0.1, 0.6, 1.0])
def test_split_invalid_fraction(fraction):
    with pytest.raises(ValueError, match=r"`holdout` must be in \(0, 0.5\]"):
        split_holdout(_uniform_positions(0, 10), (512, 512), fraction)


@pytest.fixture(scope="module")
def beads():
    rng = np.random.default_rng(4)
    grid = np.stack(np.meshgrid(np.arange(24, 240, 24), np.arange(24, 240, 24),
                                indexing="ij"), -1).reshape(-1, 2).astype(float)
    centers = grid + rng.uniform(-0.5, 0.5, grid.shape)
    img = np.full(SHAPE, 100.0)
    for c in centers:
        img += integrated_gaussian(SHAPE, c, SIGMA, 2000.0)
    img += NOISE * rng.standard_normal(SHAPE)
    return extract_patches(img, centers, R)


def _constant_model(psf):
    h, w = SHAPE
    return ProductConvolution(psf[None], np.ones((1, 2, 2)), shape=SHAPE,
                              grid=(np.array([0.0, h - 1]), np.array([0.0, w - 1])))


def test_true_model_reaches_noise_floor(beads):
    size = patch_size(R)
    c = size // 2
    truth = integrated_gaussian((size, size), (c, c), SIGMA, 1.0)
    res = heldout_residuals(_constant_model(truth), beads)
    assert isinstance(res, HeldoutResiduals)
    assert np.array_equal(res.positions, beads.centers)
    ratio = res.residual / res.noise_floor
    # measured median ratio 1.004, range 0.77-1.32 over 81 beads (floor ~0.027);
    # the floor uses the robust noise estimate of the re-sampled patch
    assert 0.7 < np.median(ratio) < 1.4
    assert 0.5 < ratio.min() and ratio.max() < 2.0
    s = res.summary()
    assert s["n_beads"] == len(beads)
    assert s["residual_mean"] == pytest.approx(res.residual.mean())
    assert s["noise_floor_median"] == pytest.approx(np.median(res.noise_floor))


def test_wrong_model_stands_above_floor(beads):
    size = patch_size(R)
    c = size // 2
    wrong = integrated_gaussian((size, size), (c, c), 1.3 * SIGMA, 1.0)
    res = heldout_residuals(_constant_model(wrong), beads)
    # a 30 % too wide PSF: measured median residual / floor = 9.1
    assert np.median(res.residual / res.noise_floor) > 3


def test_size_mismatch_raises(beads):
    psf = integrated_gaussian((15, 15), (7, 7), SIGMA, 1.0)
    with pytest.raises(ValueError, match="PSF size 15 differs from the patch size 17"):
        heldout_residuals(_constant_model(psf), beads)


def test_empty_summary():
    empty = HeldoutResiduals(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    assert empty.summary() == {"n_beads": 0}
