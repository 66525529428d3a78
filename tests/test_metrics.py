"""Tests of the PSF error metrics (core/metrics.py)."""

import numpy as np
import pytest

from napari_psfspace.core.model.operator import ProductConvolution
from napari_psfspace.core.simulation import Optics, simulate_psf
from napari_psfspace.core.simulation.metrics import (
    best_shift,
    grid_errors,
    psf_error,
    rescaled_error,
    shift_invariant_errors,
)

SIZE = 21


def test_error_of_psf_against_itself():
    t = simulate_psf({5: 0.05}, size=SIZE)
    assert rescaled_error(t, t) < 1e-7  # measured 0 (sqrt of a clipped round-off)
    assert psf_error(t, t) < 1e-6  # measured 0
    assert psf_error(t, t, align=False) < 1e-7


@pytest.mark.parametrize(
    "pixel_size, band",
    [
        # default optics (65 nm pixels, PSF core sigma ~1.5 px): measured 0.143
        (0.065, (0.12, 0.17)),
        # 100 nm pixels (sigma ~1 px): measured 0.213, the brief's "~0.3" regime
        (0.1, (0.18, 0.40)),
    ],
)
def test_subpixel_shift_is_aligned_away(pixel_size, band):
    optics = Optics(pixel_size=pixel_size)
    t = simulate_psf(size=SIZE, optics=optics)
    e = simulate_psf(size=SIZE, shift=(0.3, 0.0), optics=optics)
    unaligned = psf_error(e, t, align=False)
    assert band[0] < unaligned < band[1]
    # measured 6.1e-4 (65 nm) and 4.8e-4 (100 nm)
    assert psf_error(e, t) < 0.01
    shift, err = best_shift(e, t)
    # the estimate must move back by the 0.3 px: measured (-0.29999, 1e-5)
    assert np.abs(shift - [-0.3, 0.0]).max() < 0.01
    assert err == pytest.approx(psf_error(e, t))


def test_shift_along_columns_symmetric():
    t = simulate_psf(size=SIZE)
    e_row = simulate_psf(size=SIZE, shift=(0.3, 0.0))
    e_col = simulate_psf(size=SIZE, shift=(0.0, 0.3))
    # the aberration-free PSF is isotropic: measured identical to 1e-15
    assert abs(psf_error(e_row, t, align=False) - psf_error(e_col, t, align=False)) < 1e-9


def test_rescaled_error_scale_invariant_and_closed_form():
    rng = np.random.default_rng(0)
    t = simulate_psf({6: 0.08}, size=SIZE)
    d = rng.standard_normal(t.shape)
    d -= (d.ravel() @ t.ravel()) / (t.ravel() @ t.ravel()) * t  # orthogonal to t
    d *= 0.2 * np.linalg.norm(t) / np.linalg.norm(d)
    e = t + d
    # closed form for d orthogonal to t: err^2 = |d|^2 / (|t|^2 + |d|^2) = 0.04 / 1.04
    expected = np.sqrt(0.04 / 1.04)
    for c in (1.0, 3.7, 1e-3, 1e4):
        assert abs(rescaled_error(c * e, t) - expected) < 1e-12  # measured 1e-16
    # a negative scale is allowed too (c is free in min_c)
    assert abs(rescaled_error(-2.0 * e, t) - expected) < 1e-12
    # relative to the truth: scaling the truth changes nothing either
    assert abs(rescaled_error(e, 5.0 * t) - expected) < 1e-12
    assert rescaled_error(np.zeros_like(t), t) == 1.0


def test_zero_truth_and_shape_mismatch_raise():
    t = simulate_psf(size=SIZE)
    with pytest.raises(ValueError, match="`truth` is zero"):
        rescaled_error(t, np.zeros_like(t))
    with pytest.raises(ValueError, match=r"`estimate` and `truth`.*\(21, 21\) and \(19, 19\)"):
        psf_error(t, simulate_psf(size=19))


class _ConstantTruth:
    def __init__(self, psf_of_position):
        self._f = psf_of_position

    def psf_at(self, y, x, size):
        return self._f(y, x, size)


def test_grid_and_shift_invariant_errors():
    shape = (128, 160)
    psf = simulate_psf({5: 0.05}, size=SIZE)
    op = ProductConvolution(psf[None], np.ones((1, 2, 2)), shape=shape,
                            grid=(np.array([0.0, 127.0]), np.array([0.0, 159.0])))
    truth = _ConstantTruth(lambda y, x, size: simulate_psf({5: 0.05}, size=size))
    err = grid_errors(op, truth, n=3, align=False)
    # measured 1.2e-8: the square root of round-off in |t|^2 - c <e, t>
    assert err.shape == (3, 3) and err.max() < 1e-6
    # a truth whose astigmatism varies across the field: the mean PSF misses it
    varying = _ConstantTruth(
        lambda y, x, size: simulate_psf({5: 0.15 * (x / 159.0 - 0.5)}, size=size))
    si = shift_invariant_errors(varying, SIZE, shape, n=3, align=False)
    assert si.shape == (3, 3)
    # measured 0.020 at the edge columns (astigmatism -/+0.066 waves) and 0.037 in the
    # middle one (no astigmatism: sharper than the blurred mean)
    assert si.min() > 0.01
    # the PSF does not vary along rows, and +/- astigmatism are mirror images
    assert np.abs(si - si[:1]).max() < 1e-12
    assert abs(si[0, 0] - si[0, 2]) < 1e-6
    assert si[0, 1] > si[0, 0]
    # a field-constant truth has no shift-invariant error
    assert shift_invariant_errors(truth, SIZE, shape, n=3, align=False).max() < 1e-6


@pytest.mark.parametrize("size", [21, 53, 20])
def test_the_matrix_shift_is_the_padded_fourier_shift(size):
    """The metric's separable shift matrices equal a translation by the FFT on the same
    zero-padded grid (odd length 2 size + 3), to round-off (measured 7e-16 of the peak)."""
    from scipy import fft as sfft

    from napari_psfspace.core.simulation.metrics import _shifter

    t = simulate_psf({5: 0.05, 7: 0.05}, size=size) if size % 2 else \
        simulate_psf({5: 0.05, 7: 0.05}, size=size + 1)[:-1, :-1]
    n = 2 * size + 3
    big = np.zeros((n, n))
    big[:size, :size] = t
    spec = sfft.fft2(big)
    k = sfft.fftfreq(n)
    shifted = _shifter(t)
    for s in [(0.3, -0.7), (1.9, 0.1), (0.0, 0.0), (-2.0, 1.0)]:
        ph = np.exp(-2j * np.pi * (k[:, None] * s[0] + k[None, :] * s[1]))
        ref = sfft.ifft2(spec * ph).real[:size, :size]
        # round-off of sums of ~size terms of magnitude <= max(t): far below 1e-12
        assert np.abs(shifted(s) - ref).max() < 1e-12 * t.max() * size
