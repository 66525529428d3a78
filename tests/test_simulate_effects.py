"""Tests of the effects injectable into simulated bead images (``simulate_beads(effects=...)``).

Each effect is checked on a measured quantity against a stated bound; the
comment next to each assertion gives the value measured when it was written.
"""

import warnings

import numpy as np
import pytest
from scipy import ndimage, signal
from scipy.optimize import OptimizeWarning, curve_fit

from napari_psfspace.core.simulation import (
    EFFECTS,
    FieldAberrations,
    Optics,
    simulate_beads,
    simulate_psf,
)


def _photons(image: np.ndarray, truth) -> np.ndarray:
    """Background-subtracted photons of a camera image."""
    return (image.astype(float) - truth.offset) / truth.gain - truth.background


def _far_from_beads(truth, positions=None) -> np.ndarray:
    """Pixels farther than the render radius (3 psf_radius) + 1 from every bead."""
    yy, xx = np.indices(truth.shape)
    far = np.ones(truth.shape, bool)
    for y, x in truth.positions if positions is None else positions:
        far &= np.hypot(yy - y, xx - x) > 3 * truth.psf_radius + 1
    return far


def _window(array: np.ndarray, y: float, x: float, radius: int) -> np.ndarray:
    cy, cx = round(y), round(x)
    return array[cy - radius : cy + radius + 1, cx - radius : cx + radius + 1]


def _poly2_residual(patch: np.ndarray) -> np.ndarray:
    """Residual of the least-squares order-2 polynomial fit of a square patch."""
    yy, xx = (a.ravel() / patch.shape[0] for a in np.indices(patch.shape))
    design = np.stack([np.ones_like(yy), yy, xx, yy * yy, yy * xx, xx * xx], axis=1)
    coefs, *_ = np.linalg.lstsq(design, patch.ravel(), rcond=None)
    return patch.ravel() - design @ coefs


def _gaussian_sigma(patch: np.ndarray) -> float:
    """Width of a least-squares 2-D Gaussian + constant fit, pixels."""

    def model(yx, a, y0, x0, s, b):
        return a * np.exp(-((yx[0] - y0) ** 2 + (yx[1] - x0) ** 2) / (2 * s * s)) + b

    yx = (np.indices(patch.shape) - patch.shape[0] // 2).reshape(2, -1)
    p0 = (patch.max(), 0.0, 0.0, 2.0, 0.0)
    with warnings.catch_warnings():  # no covariance for noise-free patches: irrelevant here
        warnings.simplefilter("ignore", OptimizeWarning)
        params, _ = curve_fit(model, yx, patch.ravel(), p0=p0)
    return abs(params[3])


# --- no effects -------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 5])
def test_no_effects_is_bit_identical(seed):
    kw = dict(shape=(128, 160), n_beads=6, aberrations="moderate", seed=seed)
    image, truth = simulate_beads(**kw)
    for effects in (None, {}):
        again, truth2 = simulate_beads(**kw, effects=effects)
        assert again.dtype == image.dtype and np.array_equal(again, image)
        for name in ("positions", "amplitudes", "background", "peak_snr"):
            assert np.array_equal(getattr(truth2, name), getattr(truth, name))
        assert truth2.effects == {}


def test_observed_psf_without_effects_is_psf_at():
    _, truth = simulate_beads((96, 96), 0, aberrations="moderate")
    assert np.array_equal(truth.observed_psf_at(20.0, 70.0), truth.psf_at(20.0, 70.0))
    assert np.array_equal(
        truth.observed_psf_at(50.0, 10.0, 15, diameter=0.0), truth.psf_at(50.0, 10.0, 15)
    )


# --- validation -------------------------------------------------------------------------


def test_unknown_effect_raises():
    with pytest.raises(ValueError, match="'glare'") as info:
        simulate_beads((64, 64), 1, effects={"glare": 1.0})
    assert all(name in str(info.value) for name in EFFECTS)


@pytest.mark.parametrize(
    "name, value",
    [
        ("illumination", 1.0),
        ("illumination", 0.0),
        ("illumination", (0.5, "centre")),
        ("row_offsets", -1.0),
        ("column_offsets", np.nan),
        ("hot_pixels", -3),
        ("hot_pixels", 1.5),
        ("saturation", 70000),  # above the uint16 maximum
        ("saturation", 50.0),  # below the camera offset
        ("nonlinearity", 0.6),
        ("nonlinearity", 0.0),
        ("neighbours", 0.0),
        ("neighbours", 1.2),
        ("bead_size", -0.1),
        ("bead_size", (0.5, 0.2)),
        ("drift", 3.0),
        ("drift", (1.0, np.inf)),
        ("background_structure", "a lot"),
    ],
)
def test_invalid_effect_value_raises(name, value):
    with pytest.raises(ValueError, match=repr(name)):
        simulate_beads((64, 64), 1, effects={name: value})


# --- one test per effect ----------------------------------------------------------------


@pytest.mark.parametrize("seed", [5, 6, 7])  # a bound from one seed, judged on three
def test_illumination(seed):
    kw = dict(shape=(384, 384), n_beads=12, dtype=np.float32, seed=seed)
    image, truth = simulate_beads(**kw, effects={"illumination": 0.8})
    _, plain = simulate_beads(**kw)
    field = truth.effects["illumination_map"]
    assert field.shape == truth.shape and field.dtype == np.float32
    # The background is the smooth background times the map (float32 round-off).
    assert np.abs(truth.background - plain.background * field).max() < 1e-3
    # The photons of each bead whose window lies inside the image, with no other bead's
    # light in it, are its drawn amplitude times the map at the bead: within 5 sigma of
    # the Poisson noise of the window (its background and the bead; the read noise and
    # the light beyond the window, a fraction of a sigma, are left out of sigma). (A
    # correlation over all beads, once here, held on one seed only: windows clipped by
    # the border were empty, and neighbours added their light.)
    radius = 2 * truth.psf_radius
    pos = truth.positions
    centre = np.round(pos)
    inside = np.all((centre >= radius) & (centre + radius < np.array(truth.shape)), axis=1)
    gaps = np.hypot(*(pos[:, None] - pos[None]).transpose(2, 0, 1))
    gaps[np.diag_indices(len(pos))] = np.inf
    alone = gaps.min(axis=1) > radius + 3 * truth.psf_radius + 1  # render radius 3 psf_radius
    keep = np.flatnonzero(inside & alone)
    assert len(keep) >= 1
    photons = _photons(image, truth)
    flux = np.array([_window(photons, *pos[i], radius).sum() for i in keep])
    light = np.array([_window(truth.background, *pos[i], radius).sum() for i in keep])
    expected = plain.amplitudes[keep] * np.array([field[round(y), round(x)]
                                                   for y, x in pos[keep]])
    assert np.all(np.abs(flux - expected) < 5 * np.sqrt(light + expected))
    assert np.allclose(truth.amplitudes, plain.amplitudes * truth.effects["illumination_factors"])


@pytest.mark.parametrize("seed", [2, 3, 4])  # a bound from one seed, judged on three
def test_row_and_column_offsets(seed):
    kw = dict(shape=(256, 256), n_beads=4, background=100.0, seed=seed)
    effects = {"row_offsets": 10.0, "column_offsets": 10.0}
    image, truth = simulate_beads(**kw, effects=effects)
    plain, _ = simulate_beads(**kw)
    rows = truth.effects["row_offset_values"]
    cols = truth.effects["column_offset_values"]
    assert rows.shape == (256,) and cols.shape == (256,)
    # Offsets come after the noise, whose realisation is unchanged: exact up to rounding.
    pattern = rows[:, None] + cols[None, :]
    assert np.abs(image.astype(float) - plain - pattern).max() <= 1.0  # measured 0.999
    # Row / column medians of the bead-free region track the truth.
    far = _far_from_beads(truth)
    excess = image.astype(float) - truth.offset - truth.gain * truth.background
    excess[~far] = np.nan
    assert np.corrcoef(np.nanmedian(excess, axis=1), rows)[0, 1] > 0.95  # measured 0.977 on seed 2
    assert np.corrcoef(np.nanmedian(excess, axis=0), cols)[0, 1] > 0.95  # measured 0.986 on seed 2


def test_hot_pixels():
    kw = dict(shape=(256, 256), n_beads=12, seed=4)
    image, truth = simulate_beads(**kw, effects={"hot_pixels": 40})
    plain, _ = simulate_beads(**kw)
    where = truth.effects["hot_pixel_positions"]
    values = truth.effects["hot_pixel_values"]
    assert where.shape == (40, 2) and len(np.unique(where, axis=0)) == 40
    # Values uniform in [20 %, 100 %] of the typical bead peak (window-normalised PSF: ~10 %).
    peaks = [truth.psf_at(y, x).max() for y, x in truth.positions]
    typical = truth.gain * np.median(truth.amplitudes * np.array(peaks))
    assert 0.15 * typical < values.min() and values.max() < 1.1 * typical  # 0.23, 0.94
    rows, cols = where.T
    local = ndimage.median_filter(image.astype(float), size=5)
    read_adu = truth.gain * truth.read_noise
    noise_sd = np.sqrt(truth.gain * np.maximum(local - truth.offset, 0) + read_adu**2)
    z = (image[rows, cols] - local[rows, cols]) / noise_sd[rows, cols]
    assert z.min() > 10  # measured 38
    diff = image.astype(float) - plain
    diff[rows, cols] -= values
    assert np.abs(diff).max() <= 1.0  # measured 0.90: only the hot pixels changed
    _, fraction = simulate_beads((100, 100), 0, effects={"hot_pixels": 0.002})
    assert fraction.effects["hot_pixels"] == 20


def test_saturation():
    kw = dict(shape=(256, 256), n_beads=12, seed=4)
    image, truth = simulate_beads(**kw, effects={"saturation": 3000})
    plain, _ = simulate_beads(**kw)
    count = truth.effects["saturated_pixels"]
    assert count == np.count_nonzero(image == 3000) > 20  # measured 68
    assert image.max() == 3000 and np.array_equal(image, np.minimum(plain, 3000))


@pytest.mark.parametrize("c", [0.1, 0.3])
def test_nonlinearity(c):
    kw = dict(
        shape=(160, 160),
        n_beads=6,
        amplitude=(1e5, 2e5),
        aberrations=None,
        dtype=np.float32,
        seed=6,
    )
    image, truth = simulate_beads(**kw, effects={"nonlinearity": c})
    plain, plain_truth = simulate_beads(**kw)
    k = int(np.argmax(truth.amplitudes))
    y, x = truth.positions[k]
    radius = 2 * truth.psf_radius
    window = _window(_photons(image, truth), y, x, radius)
    window0 = _window(_photons(plain, plain_truth), y, x, radius)
    peak_drop = 1 - window.max() / window0.max()
    ratio_drop = 1 - (window.max() / window.sum()) / (window0.max() / window0.sum())
    # The brightest pixel loses the fraction c; the flux loses about c / 2 (sum e^2 / e_ref
    # over sum e is ~1/2 for a compact spot), so peak / flux drops by about c / 2.
    assert abs(peak_drop - c) < 0.02  # measured 0.095 (c=0.1), 0.294 (c=0.3)
    assert 0.35 * c < ratio_drop < 0.7 * c  # measured 0.048 (c=0.1), 0.176 (c=0.3)
    e_ref = truth.effects["nonlinearity_reference"]
    assert abs(e_ref / (plain_truth.background[round(y), round(x)] + window0.max()) - 1) < 0.02


def test_neighbours():
    image, truth = simulate_beads((256, 256), 12, seed=8, effects={"neighbours": 1.0})
    r = truth.psf_radius
    companions = truth.effects["companion_positions"]
    owners = truth.effects["companion_of"]
    assert truth.positions.shape == (12, 2) and companions.shape == (12, 2)
    distance = np.hypot(*(companions - truth.positions[owners]).T) / r
    assert distance.min() >= 0.6 and distance.max() <= 1.6  # measured 0.76-1.55
    ratio = truth.effects["companion_amplitudes"] / truth.amplitudes[owners]
    assert ratio.min() >= 0.3 and ratio.max() <= 1.0
    is_max = image == ndimage.maximum_filter(image, size=3)
    inside = [(round(y), round(x)) for y, x in companions if 2 <= y < 253 and 2 <= x < 253]
    found = [is_max[cy - 1 : cy + 2, cx - 1 : cx + 2].any() for cy, cx in inside]
    assert len(inside) >= 10 and all(found)  # measured 12 of 12 local maxima


def test_close_companions_by_distance_in_pixels():
    spec = {"fraction": 0.5, "distance_px": (1.0, 3.0), "amplitude": (0.5, 1.0)}
    _, truth = simulate_beads((256, 256), 20, seed=8, effects={"neighbours": spec})
    companions = truth.effects["companion_positions"]
    owners = truth.effects["companion_of"]
    assert len(owners) == 10
    distance = np.hypot(*(companions - truth.positions[owners]).T)
    assert distance.min() >= 1.0 and distance.max() <= 3.0
    ratio = truth.effects["companion_amplitudes"] / truth.amplitudes[owners]
    assert ratio.min() >= 0.5 and ratio.max() <= 1.0
    for bad in ({"fraction": 0.1, "distance_px": (3.0, 1.0)}, {"distance_px": (1, 3)},
                {"fraction": 0.1, "spacing": 2}):
        with pytest.raises(ValueError, match="neighbours"):
            simulate_beads((64, 64), 2, seed=0, effects={"neighbours": bad})


def test_scene_defocus_gradient_spans_the_field():
    from napari_psfspace.core.simulation.scene_set import random_scene

    shape = (256, 256)
    _, plain, _ = random_scene(3, shape=shape)
    image, truth, p = random_scene(3, shape=shape, effects={"defocus_gradient": (0.15, 0.0)})
    assert p["defocus_gradient"] == {"span_waves": 0.15, "angle_deg": 0.0}
    z4 = [truth.aberrations.coefficients(128, x, shape).get(4, 0.0)
          - plain.aberrations.coefficients(128, x, shape).get(4, 0.0) for x in (0, 255)]
    assert z4[1] - z4[0] == pytest.approx(0.15, abs=1e-9)
    # a random direction is drawn apart from the scene: positions are unchanged
    _, t2, p2 = random_scene(3, shape=shape, effects={"defocus_gradient": 0.15})
    assert 0 <= p2["defocus_gradient"]["angle_deg"] < 360
    assert np.array_equal(t2.positions, plain.positions)


@pytest.mark.parametrize("diameter", [0.2, 0.5])
def test_bead_size_closed_form_matches_direct_convolution(diameter):
    # Projected-sphere transform (Fourier, camera-pixel grid) against a direct convolution
    # of the PSF on 9x finer pixels with the cell-averaged chord-length profile, binned.
    # The difference is the direct method's discretisation: 1.0e-3 / 3.4e-4 with 5x finer
    # pixels, 2.8e-4 / 7.3e-5 with 9x, 1.5e-4 / 5.0e-5 with 13x (d = 0.2 / 0.5 um).
    coefs = {4: 0.1, 6: 0.05}
    _, truth = simulate_beads(
        (64, 64), 0, aberrations=FieldAberrations({j: (c,) for j, c in coefs.items()})
    )
    fine, size, sub = 9, 31, 4
    observed = truth.observed_psf_at(32, 32, size=size, diameter=diameter)
    step = truth.optics.pixel_size / fine
    psf_fine = simulate_psf(coefs, optics=Optics(pixel_size=step), size=size * fine)
    half = int(np.ceil(diameter / 2 / step)) + 1
    axis = (np.arange(-half, half + 1)[:, None] + (np.arange(sub) + 0.5) / sub - 0.5).ravel()
    radius2 = (axis[:, None] ** 2 + axis**2) * step**2
    chord = np.sqrt(np.clip((diameter / 2) ** 2 - radius2, 0, None))
    kernel = chord.reshape(2 * half + 1, sub, 2 * half + 1, sub).mean(axis=(1, 3))
    direct = signal.fftconvolve(psf_fine, kernel / kernel.sum(), mode="same")
    direct = direct.reshape(size, fine, size, fine).sum(axis=(1, 3))
    core = (slice(5, 26), slice(5, 26))  # away from the fine window's truncated edge
    a, b = observed[core] / observed[core].sum(), direct[core] / direct[core].sum()
    assert np.abs(a - b).max() < 1e-3 * b.max()  # measured 2.8e-4 (0.2 um), 7.3e-5 (0.5 um)
    point = truth.psf_at(32, 32, size=size)[core]
    assert np.abs(a - point / point.sum()).max() > 0.1 * b.max()  # the sphere matters: 0.18


def test_bead_size_widens_beads():
    kw = dict(
        shape=(256, 256),
        n_beads=12,
        aberrations=None,
        amplitude=5e4,
        dtype=np.float32,
        seed=9,
    )
    sigmas = {}
    for diameter in (0.0, 0.5):
        image, truth = simulate_beads(**kw, effects={"bead_size": diameter})
        photons = _photons(image, truth)
        measured = [_gaussian_sigma(_window(photons, y, x, 7)) for y, x in truth.positions]
        model = _gaussian_sigma(truth.observed_psf_at(128, 128, size=15, diameter=diameter))
        sigmas[diameter] = np.mean(measured), model
    growth = sigmas[0.5][0] / sigmas[0.0][0]
    expected = sigmas[0.5][1] / sigmas[0.0][1]
    # FWHM 3.48 px -> 5.80 px at default optics (0.5 um = 7.7 pixels).
    assert abs(growth / expected - 1) < 0.02  # measured 1.667 vs 1.672
    assert growth > 1.5
    _, truth = simulate_beads((256, 256), 20, seed=1, effects={"bead_size": (0.1, 0.4)})
    diameters = truth.effects["bead_diameters"]
    assert diameters.min() >= 0.1 and diameters.max() <= 0.4
    # Amplitude factor d^3 / E[d^3]: the bright beads are the big ones.
    _, plain = simulate_beads((256, 256), 20, seed=1)
    mean_cube = (0.4**4 - 0.1**4) / (4 * 0.3)
    assert np.allclose(truth.amplitudes, plain.amplitudes * diameters**3 / mean_cube)


def _variance_along(psf: np.ndarray, centre, direction) -> float:
    yy, xx = np.indices(psf.shape)
    t = (yy - centre[0]) * direction[0] + (xx - centre[1]) * direction[1]
    return float((psf * t * t).sum() / psf.sum())


def test_drift_model_adds_segment_variance():
    drift = (3.0, 4.0)
    _, truth = simulate_beads((64, 64), 0, aberrations=None, effects={"drift": drift})
    direction = np.array(drift) / np.hypot(*drift)
    moved, still = truth.observed_psf_at(32, 32, size=61), truth.psf_at(32, 32, size=61)
    growth = _variance_along(moved, (30, 30), direction) - _variance_along(
        still, (30, 30), direction
    )
    assert abs(growth / (25 / 12) - 1) < 0.05  # measured 0.980


def test_drift_in_image():
    drift = (3.0, 4.0)
    kw = dict(
        shape=(256, 256),
        n_beads=12,
        aberrations=None,
        amplitude=1e6,
        background=10.0,
        border=30.0,
        min_separation=50.0,
        dtype=np.float32,
        seed=10,
    )
    image, truth = simulate_beads(**kw, effects={"drift": drift})
    photons = _photons(image, truth)
    along = np.array(drift) / np.hypot(*drift)
    across = np.array([-along[1], along[0]])
    radius = 3 * truth.psf_radius
    excess = []
    for y, x in truth.positions:
        window = _window(photons, y, x, radius)
        centre = (radius + y - round(y), radius + x - round(x))
        excess.append(
            _variance_along(window, centre, along) - _variance_along(window, centre, across)
        )
    # Round aberration-free PSF: the only anisotropy is the segment variance |d|^2 / 12.
    assert abs(np.mean(excess) / (25 / 12) - 1) < 0.05  # measured 0.995 (+- 0.015)


def test_background_structure():
    kw = dict(shape=(384, 384), n_beads=6, dtype=np.float32, seed=12)
    amplitude = 50.0
    results = {}
    for effects in (None, {"background_structure": amplitude}):
        image, truth = simulate_beads(**kw, effects=effects)
        photons = (image.astype(float) - truth.offset) / truth.gain
        far = _far_from_beads(truth)
        n = 2 * truth.psf_radius
        excess, structure_residual, structure = [], [], []
        for i in range(0, truth.shape[0] - n + 1, n):
            for j in range(0, truth.shape[1] - n + 1, n):
                patch = (slice(i, i + n), slice(j, j + n))
                if not far[patch].all():
                    continue
                noise = (truth.background[patch].mean() + truth.read_noise**2) * (1 - 6 / n**2)
                excess.append(_poly2_residual(photons[patch]).var() - noise)
                if effects:
                    blobs = truth.effects["background_structure_map"][patch].astype(float)
                    structure_residual.append(_poly2_residual(blobs).var())
                    structure.append(blobs.var())
        results[effects is None] = excess, structure_residual, structure
    plain_excess = results[True][0]
    excess, structure_residual, structure = results[False]
    assert len(excess) > 50  # bead-free 2r x 2r patches
    # What the polynomial leaves in the image is the structure's own residual, which is
    # about half its patch rms; without the effect the image leaves only noise.
    assert abs(np.sqrt(np.mean(excess) / np.mean(structure_residual)) - 1) < 0.1  # meas. 0.97
    assert np.mean(structure_residual) > 0.15 * np.mean(structure)  # measured 0.20 (rms 0.45)
    assert abs(np.mean(plain_excess)) < 0.1 * np.mean(structure_residual)  # measured 0.023
    assert truth.effects["background_structure_map"].max() >= amplitude  # peak a per blob


def test_all_effects_together():
    effects = {
        "illumination": (0.5, (10.0, 200.0)),
        "row_offsets": 2.0,
        "column_offsets": 2.0,
        "hot_pixels": 10,
        "saturation": 5000,
        "nonlinearity": 0.1,
        "neighbours": 0.5,
        "bead_size": (0.1, 0.2),
        "drift": (0.5, -1.0),
        "background_structure": 20.0,
    }
    image, truth = simulate_beads((256, 256), 10, seed=3, effects=effects)
    again, _ = simulate_beads((256, 256), 10, seed=3, effects=effects)
    assert np.array_equal(image, again)
    assert image.max() == 5000
    assert np.allclose(truth.effects["illumination_centre"], (10.0, 200.0))
    assert len(truth.effects["companion_positions"]) == 5
    assert truth.effects["drift"] == (0.5, -1.0)
    observed = truth.observed_psf_at(128, 128)
    assert abs(observed.sum() - 1) < 1e-12
    assert observed.max() < truth.psf_at(128, 128).max()  # size and drift spread the peak
    # Each effect's randomness is its own: row offsets do not depend on the other effects.
    _, alone = simulate_beads((256, 256), 10, seed=3, effects={"row_offsets": 2.0})
    assert np.array_equal(alone.effects["row_offset_values"], truth.effects["row_offset_values"])
