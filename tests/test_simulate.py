"""Tests of the bead-image simulator (physics, normalisation, noise, determinism)."""

import numpy as np
import pytest

from napari_psfspace.core.simulation import (
    FieldAberrations,
    Optics,
    SimulationTruth,
    simulate_beads,
    simulate_psf,
)

OPTICS = Optics()
SMALL = dict(shape=(256, 256), n_beads=12, aberrations="moderate", seed=3)


@pytest.fixture(scope="module")
def small_sim() -> tuple[np.ndarray, SimulationTruth]:
    return simulate_beads(**SMALL)


def _centroid(psf: np.ndarray) -> np.ndarray:
    yy, xx = np.indices(psf.shape) - psf.shape[0] // 2
    return np.array([(psf * yy).sum(), (psf * xx).sum()]) / psf.sum()


def _half_max_crossing(profile: np.ndarray) -> float:
    """Distance (pixels) from profile[0] (the peak) to the half-maximum, linear interpolation."""
    half = profile[0] / 2
    i = int(np.argmax(profile < half))
    return i - 1 + (profile[i - 1] - half) / (profile[i - 1] - profile[i])


# --- optics and aberration field --------------------------------------------------------


def test_optics_validation():
    with pytest.raises(ValueError):
        Optics(na=1.6)
    with pytest.raises(ValueError):
        Optics(pixel_size=-0.1)
    assert Optics().oversampling == 1  # 65 nm pixels already Nyquist-sample the intensity
    assert Optics(pixel_size=0.2).oversampling == 2


def test_field_coordinates_convention():
    ab = FieldAberrations({4: (0.1, 1.0, 0.0), 6: (0.0, 0.0, 1.0)})
    shape = (101, 201)
    assert ab.coefficients(50, 100, shape) == pytest.approx({4: 0.1, 6: 0.0}, abs=1e-12)
    # u runs along columns (x), v along rows (y), +-1 at the border pixel centres.
    assert ab.coefficients(0, 200, shape) == pytest.approx({4: 1.1, 6: -1.0}, abs=1e-12)
    assert ab.coefficients(100, 0, shape) == pytest.approx({4: -0.9, 6: 1.0}, abs=1e-12)


def test_presets_and_random():
    assert FieldAberrations.preset("none").terms == {}
    with pytest.raises(ValueError):
        FieldAberrations.preset("bogus")
    a, b = FieldAberrations.random(0.1, seed=5), FieldAberrations.random(0.1, seed=5)
    assert a == b and hash(a) == hash(b)
    assert a != FieldAberrations.random(0.1, seed=6)


# --- single PSF -----------------------------------------------------------------------


def test_fwhm_aberration_free():
    optics = Optics(pixel_size=0.6 / (20 * 1.3))  # lambda / (20 NA): fine pixels
    psf = simulate_psf(optics=optics, size=65)
    c = 32
    width_px = _half_max_crossing(psf[c, c:]) + _half_max_crossing(psf[c, c::-1])
    expected = 0.51 * optics.wavelength / optics.na
    assert abs(width_px * optics.pixel_size / expected - 1) < 0.03


def test_normalised_and_nonnegative():
    psf = simulate_psf({4: 0.1, 6: 0.05}, size=151)
    assert psf.shape == (151, 151) and psf.dtype == np.float64
    assert psf.min() >= 0
    assert abs(psf.sum() - 1) < 0.015


def test_subpixel_shift_moves_centroid():
    shift = np.array([0.3, -0.25])
    free = simulate_psf(size=151, shift=tuple(shift))
    assert np.abs(_centroid(free) - shift).max() < 0.01
    aberrated = {4: 0.1, 7: 0.05, 6: 0.05}
    moved = _centroid(simulate_psf(aberrated, size=151, shift=tuple(shift)))
    still = _centroid(simulate_psf(aberrated, size=151))
    assert np.abs(moved - still - shift).max() < 0.01


def test_pixel_integration_is_exact():
    # A PSF on 5x smaller pixels, binned 5x5, equals the PSF on the large pixels.
    coefs = {4: 0.08, 5: 0.05, 8: 0.04}
    coarse = simulate_psf(coefs, size=31)
    fine_optics = Optics(pixel_size=OPTICS.pixel_size / 5)
    fine = simulate_psf(coefs, optics=fine_optics, size=31 * 5)
    binned = fine.reshape(31, 5, 31, 5).sum(axis=(1, 3))
    assert np.abs(binned - coarse).max() < 1e-3 * coarse.max()


def test_defocus_symmetry_and_astigmatism_orientation():
    # Vertical astigmatism (cos 2 theta) with defocus elongates along one image axis,
    # and the sign of the astigmatism swaps the axes (transpose).
    plus = simulate_psf({4: 0.1, 6: 0.1}, size=41)
    minus = simulate_psf({4: 0.1, 6: -0.1}, size=41)
    assert np.abs(plus - minus.T).max() < 1e-9 * plus.max()


# --- bead images ------------------------------------------------------------------------


def test_deterministic_with_seed(small_sim):
    image, truth = small_sim
    again, truth2 = simulate_beads(**SMALL)
    assert np.array_equal(image, again)
    assert np.array_equal(truth.positions, truth2.positions)
    other, _ = simulate_beads(**{**SMALL, "seed": 4})
    assert not np.array_equal(image, other)


def test_output_types(small_sim):
    image, truth = small_sim
    assert image.shape == (256, 256) and image.dtype == np.uint16
    assert truth.background.shape == (256, 256) and truth.background.dtype == np.float32
    assert truth.positions.shape == (12, 2) and truth.amplitudes.shape == (12,)
    assert truth.peak_snr.shape == (12,) and np.all(truth.peak_snr > 10)
    assert 2e4 <= truth.amplitudes.min() and truth.amplitudes.max() <= 6e4
    assert abs(truth.background.min() - 50) < 1e-3 and abs(truth.background.max() - 150) < 1e-3
    img32, _ = simulate_beads(**SMALL, dtype=np.float32)
    assert img32.dtype == np.float32
    assert not np.allclose(img32, np.rint(img32))  # float output is not rounded


def test_positions_respect_border_and_separation(small_sim):
    _, truth = small_sim
    r = truth.psf_radius
    pos = truth.positions
    assert pos.min() >= r and pos.max() <= 255 - r
    dist = np.hypot(*(pos[:, None, :] - pos[None, :, :]).transpose(2, 0, 1))
    assert dist[np.triu_indices(len(pos), 1)].min() >= 2.5 * r
    _, custom = simulate_beads(
        (128, 128), 10, aberrations=None, min_separation=20.0, border=30.0, seed=1
    )
    pos = custom.positions
    dist = np.hypot(*(pos[:, None, :] - pos[None, :, :]).transpose(2, 0, 1))
    assert pos.min() >= 30 and pos.max() <= 97 and dist[np.triu_indices(10, 1)].min() >= 20


def test_noise_is_poisson_gaussian(small_sim):
    image, truth = small_sim
    yy, xx = np.indices(truth.shape)
    far = np.ones(truth.shape, bool)
    for y, x in truth.positions:  # beads are rendered within 3 psf_radius of their centre
        far &= np.hypot(yy - y, xx - x) > 3 * truth.psf_radius + 1
    assert far.sum() > 5000
    g, bg = truth.gain, truth.background.astype(float)
    residual = image.astype(float) - truth.offset - g * bg
    expected_var = np.mean(g * g * bg[far]) + (g * truth.read_noise) ** 2
    assert abs(residual[far].mean()) < 0.5
    assert abs(residual[far].var() / expected_var - 1) < 0.1


def test_bead_photometry():
    # Isolated beads: background-subtracted photons in a window around each bead equal
    # amplitude x (PSF energy in the window), up to Poisson + read noise (z-scores).
    image, truth = simulate_beads(
        (320, 320), 4, min_separation=110.0, border=40.0, dtype=np.float32, seed=7
    )
    photons = (image.astype(float) - truth.offset) / truth.gain - truth.background
    radius = 2 * truth.psf_radius
    ratios, zscores = [], []
    for (y, x), amp in zip(truth.positions, truth.amplitudes, strict=True):
        cy, cx = round(y), round(x)
        win = (slice(cy - radius, cy + radius + 1), slice(cx - radius, cx + radius + 1))
        coefs = truth.aberrations.coefficients(y, x, truth.shape)
        psf = simulate_psf(coefs, optics=truth.optics, size=2 * radius + 1, shift=(y - cy, x - cx))
        expected = amp * psf.sum()
        variance = (truth.background[win] + amp * psf).sum() + psf.size * truth.read_noise**2
        ratios.append(photons[win].sum() / expected)
        zscores.append((photons[win].sum() - expected) / np.sqrt(variance))
    assert np.abs(zscores).max() < 4
    assert abs(np.mean(ratios) - 1) < 0.02


def test_truth_psfs_match_simulate_psf(small_sim):
    _, truth = small_sim
    y, x = 40.0, 200.0
    psf = truth.psf_at(y, x)
    assert psf.shape == (2 * truth.psf_radius + 1,) * 2
    assert abs(psf.sum() - 1) < 1e-12
    direct = simulate_psf(truth.aberrations.coefficients(y, x, truth.shape), size=psf.shape[0])
    assert np.abs(psf - direct / direct.sum()).max() < 1e-12
    ys, xs, grid = truth.psf_grid(3, 4, size=15)
    assert grid.shape == (3, 4, 15, 15)
    assert ys[0] == truth.psf_radius and xs[-1] == 255 - truth.psf_radius
    assert np.abs(grid[2, 1] - truth.psf_at(ys[2], xs[1], size=15)).max() < 1e-12


def test_psf_radius_of_presets():
    radius = {
        n: simulate_beads((64, 64), 0, aberrations=n)[1].psf_radius
        for n in ("none", "moderate", "strong")
    }
    assert radius["none"] >= 4
    assert 10 <= radius["moderate"] <= 14
    assert 18 <= radius["strong"] <= 24


@pytest.mark.parametrize("preset, bound", [("moderate", 0.15), ("strong", 0.3)])
def test_field_variation_is_real(preset, bound):
    # The best single shift-invariant PSF misses the true PSFs by a relative l2 error >= bound.
    _, truth = simulate_beads((1024, 1024), 0, aberrations=preset)
    _, _, psfs = truth.psf_grid(8, 8)
    psfs = psfs.reshape(64, -1)
    mean = psfs.mean(axis=0)
    scale = psfs @ mean / (mean @ mean)
    error = np.linalg.norm(scale[:, None] * mean - psfs) / np.linalg.norm(psfs)
    assert error >= bound


def test_impossible_placement_raises():
    with pytest.raises(ValueError, match="n_beads"):
        simulate_beads((128, 128), 500, aberrations=None, seed=0)
    with pytest.raises(ValueError, match="n_beads"):
        simulate_beads((64, 64), 2, aberrations=None, border=40.0)
