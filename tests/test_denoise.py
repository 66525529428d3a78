"""Noise-aware learning (core/denoise.py): the filters on known signals, and the gain of
the whole estimate at low signal per pixel on a seeded simulated field."""

import numpy as np
import pytest

import napari_psfspace as ps
from napari_psfspace.core.beads.window import bump_window
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model.denoise import band_limit, refit_basis
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.simulation.metrics import evaluate_against_truth


def _gaussians(k, p=25, seed=0):
    """K sum-1 Gaussian spots of slightly different widths, and a window."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:p, :p] - p // 2
    widths = 1.6 + 0.4 * rng.random(k)
    psf = np.exp(-(y**2 + x**2)[None] / (2 * widths[:, None, None] ** 2))
    win = bump_window(p, 10, 12)
    psf = psf * win
    return psf / psf.sum(axis=(1, 2), keepdims=True), win


def test_band_limit_is_identity_without_noise():
    psf, win = _gaussians(30)
    out, info = band_limit(psf, np.zeros(30), win)
    np.testing.assert_allclose(out, psf, atol=1e-12)
    assert info["noise_power"] == 0


def test_band_limit_removes_most_of_the_noise():
    psf, win = _gaussians(60)
    rng = np.random.default_rng(1)
    sd = np.full(60, 0.3 * psf.max())  # peak SNR about 3 per bead
    noisy = psf + sd[:, None, None] * rng.standard_normal(psf.shape) * win
    out, info = band_limit(noisy, sd, win)
    before = np.linalg.norm(noisy - psf) / np.linalg.norm(psf)
    after = np.linalg.norm(out - psf) / np.linalg.norm(psf)
    # measured (seed 1): 2.29 -> 0.52, passband 0.06 of the plane
    assert after <= 0.45 * before
    assert 0.02 <= info["passband"] <= 0.3


@pytest.mark.parametrize("p", [24, 25])
def test_band_limit_on_half_the_plane_is_the_whole_plane_filter(p):
    """The filter on ``rfft2``'s half plane (its power mirrored for the smoothing that
    wraps) equals the Wiener filter written on numpy's whole-plane complex FFT, for
    even and odd patches, to rounding."""
    from scipy import ndimage as ndi

    from napari_psfspace.core.model.denoise import NOISE_QUANTILE, patch_noise

    psf, _ = _gaussians(40, p=p, seed=4)
    win = bump_window(p, p // 2 - 2, p // 2)
    rng = np.random.default_rng(5)
    sd = 0.2 * psf.max() * (0.5 + rng.random(40))
    noisy = psf * win + sd[:, None, None] * rng.standard_normal(psf.shape) * win
    out, info = band_limit(noisy, sd, win)
    noise = patch_noise(sd, win)
    spectra = np.fft.fft2(noisy)
    w = 1.0 / noise
    power = np.einsum("k,kij->ij", w, np.abs(spectra) ** 2 - noise[:, None, None]) / w.sum()
    s = np.maximum(ndi.uniform_filter(power, 3, mode="wrap"), 0.0)
    n_typ = float(np.quantile(noise, NOISE_QUANTILE))
    gain = s / (s + n_typ)
    ref = np.fft.ifft2(spectra * gain[None])
    assert np.abs(ref.imag).max() <= 1e-12 * np.abs(ref.real).max()  # the gain is symmetric
    np.testing.assert_allclose(out, ref.real, rtol=0, atol=1e-12 * np.abs(ref.real).max())
    assert info["passband"] == float(np.mean(gain > 0.5))


def test_refit_basis_recovers_known_images_and_shrinks_noise():
    rng = np.random.default_rng(2)
    psf, win = _gaussians(2, p=25, seed=3)
    h = psf.copy()  # two "basis images"
    a = np.column_stack([np.ones(200), rng.uniform(-0.5, 0.5, 200)])
    clean = np.einsum("ki,ipq->kpq", a, h)
    exact, _ = refit_basis(clean, a, np.zeros(200), win, shrink=False)
    np.testing.assert_allclose(exact, h, atol=1e-10)
    sd = np.full(200, 0.5 * h.max())
    noisy = clean + sd[:, None, None] * rng.standard_normal(clean.shape) * win
    raw, info = refit_basis(noisy, a, sd, win, shrink=False)
    shrunk, _ = refit_basis(noisy, a, sd, win)
    err_raw = np.linalg.norm(raw[0] - h[0]) / np.linalg.norm(h[0])
    err_shrunk = np.linalg.norm(shrunk[0] - h[0]) / np.linalg.norm(h[0])
    # the stated noise matches the measured one (0.228 vs 0.229), shrinkage halves it (0.108)
    assert info["noise_rel"][0] == pytest.approx(err_raw, rel=0.2)
    assert err_shrunk <= 0.6 * err_raw


def test_low_signal_estimate_gains_from_denoising():
    # bench "x0.1 photons" case at a smaller size: peak SNR about 11
    image, truth = ps.simulate_beads((768, 768), 90, aberrations="moderate", seed=0,
                                     amplitude=(2e3, 6e3))
    err = {}
    for dn in (False, True):
        est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius, denoise=dn))
        err[dn] = evaluate_against_truth(est.operator, truth, 8)["aligned"]["mean"]
        meta = est.operator.metadata["denoise"]
        assert (meta is None) == (not dn)
    # measured (seed 0, peak SNR 10.4): 0.123 plain -> 0.083 denoised
    assert err[True] <= 0.8 * err[False]
    assert err[True] <= 0.10
