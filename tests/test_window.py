"""Tests of the radial bump window (core/window.py, paper Appendix A)."""

import numpy as np
import pytest

from napari_psfspace.core.beads.window import bump, bump_window, radial_distance

R, R_EXT = 5.0, 6.0


def test_bump_plateau_and_zero():
    t = np.linspace(0, 20, 2001)
    m = bump(t, R, R_EXT)
    assert np.all(m[t <= R] == 1.0)
    assert np.all(m[t >= R_EXT] == 0.0)
    inside = (t > R) & (t < R_EXT)
    assert np.all((m[inside] > 0) & (m[inside] < 1))


def test_bump_monotone_in_unit_interval():
    t = np.linspace(0, 10, 10001)
    m = bump(t, R, R_EXT)
    assert m.min() >= 0 and m.max() <= 1
    assert np.all(np.diff(m) <= 0)


def test_bump_continuous_at_both_radii():
    eps = 1e-4
    # at r: m = exp(1 - 1/(1 - s^2)) ~ 1 - s^2 with s = eps/(r_ext - r) = 1e-4
    near_r = bump(np.array([R - eps, R + eps]), R, R_EXT)
    assert abs(near_r[0] - near_r[1]) < 1e-7  # measured 1e-8
    # at r_ext the bump is flat to all orders: at s = 1 - 0.05, m = exp(1 - 10.26) ~ 1e-4
    near_ext = bump(np.array([R_EXT - 0.05, R_EXT - eps, R_EXT + eps]), R, R_EXT)
    assert near_ext[0] < 2e-4  # measured 9.5e-5
    assert near_ext[1] < 1e-300 and near_ext[2] == 0.0
    # and the exact formula in the middle: s = 0.5 -> exp(1 - 4/3)
    assert bump(R + 0.5, R, R_EXT) == pytest.approx(np.exp(-1 / 3), rel=1e-12)


def test_bump_keeps_shape():
    t = np.arange(12.0).reshape(3, 4)
    assert bump(t, 2.0, 5.0).shape == (3, 4)


@pytest.mark.parametrize("r, r_ext", [(0.0, 5.0), (-1.0, 5.0), (5.0, 5.0), (6.0, 5.0)])
def test_invalid_radii_raise(r, r_ext):
    with pytest.raises(ValueError, match="`r` and `r_ext`"):
        bump(np.arange(3.0), r, r_ext)


def test_radial_distance_and_window():
    d = radial_distance(7)
    assert d[3, 3] == 0 and d[3, 6] == 3 and d[0, 0] == pytest.approx(np.hypot(3, 3))
    w = bump_window(15, 4.0, 6.0)
    assert w.shape == (15, 15) and w[7, 7] == 1.0 and w[7, 0] == 0.0
    assert np.array_equal(w, w.T) and np.array_equal(w, w[::-1])
