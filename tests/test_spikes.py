"""Hot pixels and cosmic rays: narrower than any optics can form, found and masked."""

import numpy as np
import pytest

import napari_psfspace as ps
from napari_psfspace.core.beads.spikes import (
    MIN_THIRD_RATIO,
    find_spikes,
    inpaint_pixels,
    is_integer_valued,
    pixel_noise_sd,
)
from napari_psfspace.core.simulation import Optics, simulate_psf


@pytest.mark.parametrize(("sampling", "least"), [(1.0, 0.54), (2.0, 0.13), (2.2, 0.10)])
def test_a_band_limited_spot_spreads_over_three_pixels(sampling, least):
    """The module's premise, measured: the third brightest pixel of the 3 x 3
    neighbourhood of an aberration-free spot's maximum, over sub-pixel offsets, at pixels
    ``sampling`` times Nyquist's ``lambda / (4 NA)``."""
    optics = Optics(na=1.4, wavelength=0.6, pixel_size=sampling * 0.6 / (4 * 1.4))
    ratios = []
    for dy in np.linspace(0, 0.5, 6):
        for dx in np.linspace(0, 0.5, 6):
            psf = simulate_psf(optics=optics, size=15, shift=(dy, dx))
            top = np.sort(psf[6:9, 6:9].ravel())[::-1]
            ratios.append(top[2] / top[0])
    assert least <= min(ratios) < least + 0.01
    assert MIN_THIRD_RATIO <= least


@pytest.mark.parametrize("fraction", [0.0005, 0.001])
def test_hot_pixels_found_and_no_bead_taken_for_one(fraction):
    hot, truth = ps.simulate_beads((512, 512), 40, aberrations="moderate", seed=4,
                                   effects={"hot_pixels": (fraction, (1.0, 5.0))})
    where = truth.effects["hot_pixel_positions"]
    found = {tuple(p) for p in find_spikes(hot).tolist()}
    true = {tuple(p) for p in where.tolist()}
    # measured: 130 of 131 and 262 of 262 found, nothing else (border pixels included)
    assert len(found & true) >= 0.95 * len(true)
    assert len(found - true) <= 2
    near_bead = [p for p in found - true
                 if np.hypot(*(truth.positions - np.array(p)).T).min() < 2]
    assert near_bead == []


@pytest.mark.parametrize("sampling", [1.0, 2.0, 2.2])
def test_sharp_beads_are_not_spikes(sampling):
    """Beads imaged at up to 2.2 x Nyquist, bright and faint: none is a spike."""
    optics = Optics(na=1.4, wavelength=0.6, pixel_size=sampling * 0.6 / (4 * 1.4))
    image, truth = ps.simulate_beads((384, 384), 50, aberrations=None, optics=optics,
                                     amplitude=(300, 3e5), seed=5)
    assert len(find_spikes(image)) == 0


def test_a_two_pixel_cosmic_ray_is_one_event():
    rng = np.random.default_rng(0)
    image = rng.poisson(100, (64, 64)).astype(np.uint16)
    image[30, 30] += 2000
    image[30, 31] += 1700
    image[10, 50] += 900
    assert {tuple(p) for p in find_spikes(image).tolist()} == {(30, 30), (30, 31), (10, 50)}


def test_noise_sd_never_collapses_on_integers():
    flat = np.full((200, 200), 2, np.uint8)
    flat[::7, ::5] = 3  # a nearly constant integer background: MAD 0
    assert is_integer_valued(flat) and is_integer_valued(flat.astype(np.float32))
    assert pixel_noise_sd(flat) == pytest.approx(np.sqrt(1 / 12))
    noisy = np.random.default_rng(1).normal(100, 4, (300, 300))
    assert not is_integer_valued(noisy)
    assert pixel_noise_sd(noisy) == pytest.approx(4.0, rel=0.05)


def test_inpainting_uses_the_unmasked_neighbours():
    image = np.arange(25, dtype=float).reshape(5, 5)
    image[2, 2] = 1e6
    image[2, 3] = 1e6
    out = inpaint_pixels(image, [[2, 2], [2, 3]])
    assert out[2, 2] == np.median([6, 7, 8, 11, 16, 17, 18])
    assert out[2, 3] == np.median([7, 8, 9, 14, 17, 18, 19])
    assert image[2, 2] == 1e6  # a copy
