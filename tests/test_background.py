"""Tests of the polynomial background fit (core/background.py, paper Appendix B)."""

import numpy as np
import pytest

from napari_psfspace.core.beads.background import fit_background, monomials
from napari_psfspace.core.beads.window import bump_window

P, R = 25, 9.0


def _poly(coef, size):
    u = np.linspace(-1.0, 1.0, size)
    y, x = np.meshgrid(u, u, indexing="ij")
    c0, cx, cy, cxx, cxy, cyy = coef
    return c0 + cx * x + cy * y + cxx * x**2 + cxy * x * y + cyy * y**2


def test_monomials_columns():
    assert monomials(P, 0).shape == (P * P, 1)
    assert monomials(P, 1).shape == (P * P, 3)
    assert monomials(P, 2).shape == (P * P, 6)
    assert monomials(P, 3).shape == (P * P, 10)
    m = monomials(5, 2)
    assert np.all(m[:, 0] == 1)  # constant term first
    # every column is a distinct monomial: full column rank
    assert np.linalg.matrix_rank(m) == 6
    # coordinates span [-1, 1]
    assert m[:, 1:3].min() == -1 and m[:, 1:3].max() == 1
    with pytest.raises(ValueError, match="`order`"):
        monomials(5, -1)


def test_recovers_order2_polynomial_under_a_bump():
    rng = np.random.default_rng(0)
    k = 6
    truth = np.array([_poly(rng.normal(size=6) * [10, 3, 3, 2, 2, 2], P) for _ in range(k)])
    # compact bump strictly inside radius R (the window vanishes beyond R)
    bumps = rng.uniform(5, 50, k)[:, None, None] * bump_window(P, 0.5 * R, R)
    bg = fit_background(truth + bumps, R)
    err = np.abs(bg - truth).max()
    assert err < 1e-10  # measured 5e-14 on seed 0 (rounding only)
    assert bg.shape == truth.shape and bg.dtype == np.float64


def test_order_zero_is_mean_of_outside():
    rng = np.random.default_rng(1)
    patch = rng.normal(size=(1, P, P))
    d = np.hypot(*np.meshgrid(np.arange(P) - P // 2, np.arange(P) - P // 2, indexing="ij"))
    bg = fit_background(patch, R, order=0)
    assert np.abs(bg - patch[0][d > R].mean()).max() < 1e-12  # measured 1e-16


def test_float32_dtype_kept():
    patch = np.ones((2, P, P), dtype=np.float32)
    assert fit_background(patch, R).dtype == np.float32


def test_too_small_patch_raises():
    # a 7 x 7 patch with r = 4 has only the 4 corners outside: 4 < 2 * 6
    with pytest.raises(ValueError, match="too few to fit a background polynomial of order 2"):
        fit_background(np.zeros((1, 7, 7)), 4.0)


def test_non_square_patch_raises():
    with pytest.raises(ValueError, match="`patches` must be square"):
        fit_background(np.zeros((1, 7, 9)), 2.0)
