"""The background plane on a ring beyond the window (core/beads/background.ring_background)
against known truths: an exact plane, a wing the paper's polynomial takes for background,
the image's edge and a stray source in the ring."""

import numpy as np

from napari_psfspace.core.beads.background import ring_background
from napari_psfspace.core.beads.patches import extract_patches, patch_size
from napari_psfspace.core.beads.window import bump_window


def _lorentz_bead(shape, center, width, flux=1e4):
    """A bead whose wings fall as the distance to the power -3 (as an Airy pattern's
    envelope): a tenth of its light or more lies beyond a few widths."""
    y, x = np.indices(shape, dtype=np.float64)
    rho2 = (y - center[0]) ** 2 + (x - center[1]) ** 2
    bead = (1.0 + rho2 / width**2) ** -1.5
    return flux * bead / bead.sum()


def test_a_plane_is_recovered_exactly_on_the_patch_grid():
    shape, c, r = (96, 96), np.array([[47.3, 50.6]]), 8.0
    y, x = np.indices(shape, dtype=np.float64)
    plane = 100.0 + 0.5 * y - 0.25 * x
    size = patch_size(r)
    bg = ring_background(plane, c, r, 1.2 * r, size)
    off = np.arange(size) - size // 2
    want = 100.0 + 0.5 * (c[0, 0] + off)[:, None] - 0.25 * (c[0, 1] + off)[None, :]
    # exact arithmetic up to the solve's rounding (values near 100, a 3 x 3 system)
    np.testing.assert_allclose(bg[0], want, rtol=0, atol=1e-9)


def test_the_ring_takes_less_of_the_wings_than_the_papers_polynomial():
    shape, c, r = (128, 128), np.array([64.0, 64.0]), 10.0
    bead = _lorentz_bead(shape, c, width=2.5)
    image = bead + 50.0
    size = patch_size(r)
    half = size // 2
    window = bump_window(size, r, 1.2 * r)
    truth = bead[64 - half:64 + half + 1, 64 - half:64 + half + 1] * window
    truth /= truth.sum()
    errs = {}
    for kind in ("ring", "patch"):
        p = extract_patches(image, c[None], r, background=kind)
        errs[kind] = np.linalg.norm(p.psf[0] - truth) / np.linalg.norm(truth)
    # the ring starts at 1.2 r, where the wing is (1 / 1.2)^3 = 0.58 of its level at r,
    # and its plane cannot bend under the core: its error must be the smaller by far
    assert errs["ring"] < 0.5 * errs["patch"], errs


def test_a_bead_by_the_edge_is_fitted_on_the_pixels_inside_the_image():
    shape, r = (80, 80), 6.0
    y, x = np.indices(shape, dtype=np.float64)
    image = 20.0 + 0.1 * y + 0.2 * x
    c = np.array([[7.0, 40.0]])  # the ring reaches 3 px past the top edge
    size = patch_size(r)
    bg = ring_background(image, c, r, 1.2 * r, size)
    off = np.arange(size) - size // 2
    want = 20.0 + 0.1 * (7.0 + off)[:, None] + 0.2 * (40.0 + off)[None, :]
    np.testing.assert_allclose(bg[0], want, atol=1e-9)


def test_a_stray_source_in_the_ring_is_left_out():
    shape, r = (96, 96), 8.0
    rng = np.random.default_rng(3)
    image = 100.0 + rng.normal(0, 1.0, shape)
    image[48 + 12, 48 - 2:48 + 3] += 400.0  # a bright streak in the ring (at 1.5 r)
    size = patch_size(r)
    bg = ring_background(image, np.array([[48.0, 48.0]]), r, 1.2 * r, size)
    # 5 of the ring's ~450 pixels at +400 would lift a least-squares level by ~4; left
    # out, the level is the noise's mean over ~450 pixels: sd 1 / sqrt(450) < 0.05
    assert abs(bg[0, size // 2, size // 2] - 100.0) < 0.25


def test_a_neighbours_light_is_taken_out_with_the_models_psf():
    """ModelLight against a known truth: an elongated neighbour's light at a patch's
    pixels is its PSF at its sub-pixel offset, times its light."""
    from napari_psfspace.core.model.deblend import ModelLight, crowded

    size = 21
    g = np.arange(size) - size // 2
    psf = np.exp(-0.5 * (g[:, None] ** 2 / 2.0**2 + g[None, :] ** 2 / 4.0**2))
    psf /= psf.sum()

    class Constant:  # a model whose PSF is the same everywhere
        psf_size = size

        def psf_at(self, y, x):
            return psf

    light = ModelLight(Constant(), np.array([[50.0, 50.0], [50.0, 62.25]]),
                       np.array([1e3, 2e3]))
    pts = np.array([[50.0, 60.25], [52.0, 62.25], [50.0, 50.0]])
    got = light.around(np.array([50.0, 50.0]), pts)
    # the bead itself (at the centre) is not its own neighbour; the neighbour's PSF is
    # sampled at whole-pixel offsets here: (0, -2), (2, 0) and (0, -12.25), beyond reach
    want = 2e3 * np.array([psf[10, 8], psf[12, 10], 0.0])
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    assert crowded(np.array([0]), np.array([[0.0, 0.0], [0.0, 20.0]]), size)
    assert not crowded(np.array([0]), np.array([[0.0, 0.0], [0.0, 30.0]]), size)


def test_a_bead_the_ring_leaves_no_light_takes_its_patchs_background():
    """A faint bead in a dark hole of bright structure: the ring, on the structure, lies
    above the bead's own surround; that bead falls back on the paper's background."""
    shape, c, r = (128, 128), np.array([[64.0, 64.0]]), 8.0
    y, x = np.indices(shape, dtype=np.float64)
    image = np.where(np.hypot(y - 64, x - 64) < 1.5 * r, 100.0, 300.0)
    image += _lorentz_bead(shape, c[0], width=1.5, flux=2e3)
    ring = extract_patches(image, c, r)
    patch = extract_patches(image, c, r, background="patch")
    plane = ring_background(image, c, r, 1.2 * r, ring.size)
    window = bump_window(ring.size, r, 1.2 * r)
    assert ((ring.raw - plane) * window).sum() <= 0  # the ring alone leaves it no light
    assert patch.flux[0] > 0 and ring.flux[0] == patch.flux[0]
    np.testing.assert_array_equal(ring.psf, patch.psf)


def test_a_quantised_background_is_not_pulled_to_its_commonest_level():
    """An 8-bit camera at low gain: the background is 12.4 ADU with 0.35 ADU of noise,
    so most ring pixels read 12 and the ring's MAD is 0. The clip must not leave only
    the 12s (a level 0.4 ADU low over the whole patch): its scale has the step of the
    levels as a floor. Rounded Gaussian noise of sd 0.35 step dithers the levels, whose
    mean then lies within 0.03 of the truth; the ring's ~450 pixels of sd 0.46 (noise
    and rounding) give the plane's level an sd of about 0.02: 0.1 is 4 sd beyond."""
    from napari_psfspace.core.beads.background import value_step

    shape, r = (96, 96), 8.0
    rng = np.random.default_rng(5)
    truth = 12.4
    image = np.round(truth + rng.normal(0, 0.35, shape))
    size = patch_size(r)
    ring = np.hypot(*np.mgrid[-12:13, -12:13]) > 1.2 * r
    window = image[48 - 12:48 + 13, 48 - 12:48 + 13]
    assert np.median(np.abs(window[ring] - np.median(window[ring]))) == 0.0  # the case
    bg = ring_background(image, np.array([[48.0, 48.0]]), r, 1.2 * r, size)
    assert abs(bg[0, size // 2, size // 2] - truth) < 0.1
    assert value_step(image) == 1.0
    assert value_step(0.25 * image + 3.0) == 0.25
    assert value_step(rng.normal(size=shape)) == 0.0



def _airy_beads(shape, centers, first_zero, flux=4e4):
    """Beads imaged by a clear circular aperture (the Airy pattern, from scipy's Bessel
    function, sampled 3 x 3 in each pixel): their rings' light falls as the distance to
    the power -3 on average."""
    from scipy.special import j1

    sub = (np.arange(3) - 1.0) / 3.0
    y, x = np.indices(shape, dtype=np.float64)
    out = np.zeros(shape)
    for cy, cx in centers:
        acc = np.zeros(shape)
        for dy in sub:
            for dx in sub:
                v = 3.8317 * np.hypot(y + dy - cy, x + dx - cx) / first_zero
                v = np.where(v == 0, 1e-12, v)
                acc += (2 * j1(v) / v) ** 2
        out += flux * acc / acc.sum()
    return out


def test_a_beads_own_wings_do_not_lift_its_background():
    shape, r = (160, 160), 10.0
    centers = np.array([[50.3, 49.6], [50.0, 110.2], [110.4, 50.1], [109.7, 109.8]])
    beads = _airy_beads(shape, centers, first_zero=2.5)
    image = beads + 100.0
    size = patch_size(r)
    bg = ring_background(image, centers, r, 1.2 * r, size)
    d = np.hypot(*(np.indices(shape) - centers[0][:, None, None]))
    own = beads[(d > 1.2 * r) & (d <= 1.6 * r)].mean()  # the plane's lift without the wings
    lift = bg.mean(axis=(1, 2)) - 100.0
    # the wings' fall-off is fitted as a power -3 with one scale for the image: the Airy
    # rings' ripple about that envelope leaves a few per cent of the level
    assert own > 0.2, own  # the ring holds light worth correcting
    assert np.all(np.abs(lift) < 0.15 * own), (lift, own)


def test_beads_without_wings_keep_the_plane():
    shape, r = (160, 160), 10.0
    centers = np.array([[50.3, 49.6], [50.0, 110.2], [110.4, 50.1], [109.7, 109.8]])
    y, x = np.indices(shape, dtype=np.float64)
    plane = 100.0 + 0.05 * y - 0.02 * x
    image = plane + np.random.default_rng(5).normal(0.0, 1.0, shape)
    for cy, cx in centers:  # Gaussian beads (sd 2 px): no light left at 1.2 r = 6 sd
        image += 4e4 / (2 * np.pi * 4) * np.exp(-((y - cy) ** 2 + (x - cx) ** 2) / 8)
    size = patch_size(r)
    bg = ring_background(image, centers, r, 1.2 * r, size)
    at = np.round(centers).astype(int)
    # the level is the mean of ~450 ring pixels of sd 1 (0.05) whatever the wings' scale
    # fitted from noise: 5 sd of it
    np.testing.assert_allclose(bg[:, size // 2, size // 2], plane[at[:, 0], at[:, 1]],
                               atol=0.25)


def test_beads_that_disagree_on_their_wings_keep_the_plane(monkeypatch):
    """Gaussian beads (no wings) on a background that curves up about half of them and
    down about the others: each bead's ring reads a wing of its own sign, the beads'
    scatter about their common scale is as large as the scale, and the plane alone is
    kept, to the last digit."""
    from napari_psfspace.core.beads import background

    shape, r = (240, 240), 10.0
    cy, cx = np.meshgrid(np.arange(45.0, 200.0, 30.0), np.arange(45.0, 200.0, 30.0),
                         indexing="ij")
    centers = np.stack([cy.ravel(), cx.ravel()], axis=1) + 0.3
    y, x = np.indices(shape, dtype=np.float64)
    image = 100.0 + 5.0 * np.cos(2 * np.pi * y / 60) * np.cos(2 * np.pi * x / 60)
    for c in centers:
        image += 4e4 / (8 * np.pi) * np.exp(-((y - c[0]) ** 2 + (x - c[1]) ** 2) / 8)
    size = patch_size(r)
    with_wings = ring_background(image, centers, r, 1.2 * r, size)
    monkeypatch.setattr(background, "OWN_WINGS", False)
    plane = ring_background(image, centers, r, 1.2 * r, size)
    np.testing.assert_array_equal(with_wings, plane)


def test_the_rings_noise_is_read_from_how_often_a_level_is_left():
    """``rounding_noise`` against rounded Gaussian noise of known sd: within 10 % where
    both tails hold at least 1 % of the 40,000 pixels (each share's standard error is
    then under 5 % of it, and a quantile's error under 2 % of sd), an upper estimate
    where one tail is empty (its share is floored at half a pixel's)."""
    from scipy.stats import norm

    from napari_psfspace.core.beads.background import rounding_noise

    rng = np.random.default_rng(11)
    for sd in (0.15, 0.3, 0.6, 2.0):
        for delta in (0.0, 0.2, 0.4):
            vals = np.round(7.0 + delta + rng.normal(0.0, sd, (100, 400)))
            got = rounding_noise(vals, np.ones(vals.shape, bool), 1.0)
            both = min(norm.sf((0.5 - delta) / sd), norm.sf((0.5 + delta) / sd)) >= 0.01
            if both:
                assert abs(got / sd - 1.0) < 0.1, (sd, delta, got)
            else:
                assert got > 0.9 * sd, (sd, delta, got)
    # the step's unit: the same noise on a lattice of step 0.25 reads a quarter of it
    vals = np.round(7.2 + rng.normal(0.0, 0.6, (100, 400)))
    one = rounding_noise(vals, np.ones(vals.shape, bool), 1.0)
    quarter = rounding_noise(0.25 * vals + 3.0, np.ones(vals.shape, bool), 0.25)
    assert abs(quarter - 0.25 * one) <= 1e-12 * one


def test_noise_far_below_a_step_keeps_the_plane(monkeypatch):
    """Airy beads on an 8-bit camera at 20 photons an ADU: the background's noise is
    0.14 of a step, so the rings read the rounding's level and the wings' fall-off is
    rounded away. The plane alone is kept, to the last digit; with the rule off, the
    wings' fit moves it (the test can fail)."""
    from napari_psfspace.core.beads import background

    shape, r = (160, 160), 10.0
    centers = np.array([[50.3, 49.6], [50.0, 110.2], [110.4, 50.1], [109.7, 109.8]])
    rng = np.random.default_rng(2)
    photons = _airy_beads(shape, centers, first_zero=2.5, flux=4e4) + 4.6
    image = np.round(10.0 + 0.05 * rng.poisson(photons) + rng.normal(0.0, 0.09, shape))
    size = patch_size(r)
    kept = ring_background(image, centers, r, 1.2 * r, size)
    monkeypatch.setattr(background, "OWN_WINGS", False)
    plane = ring_background(image, centers, r, 1.2 * r, size)
    np.testing.assert_array_equal(kept, plane)
    monkeypatch.setattr(background, "OWN_WINGS", True)
    monkeypatch.setattr(background, "SUBSTEP_SD", 0.0)
    assert not np.array_equal(ring_background(image, centers, r, 1.2 * r, size), plane)
