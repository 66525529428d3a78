"""Tests of the clipped Voronoi cell areas (core/voronoi.py, paper Appendix C)."""

import numpy as np
import pytest

from napari_psfspace.core.model.voronoi import voronoi_areas


def test_areas_sum_to_field():
    rng = np.random.default_rng(0)
    shape = (300, 200)
    pts = rng.uniform([-0.5, -0.5], [shape[0] - 0.5, shape[1] - 0.5], size=(80, 2))
    areas = voronoi_areas(pts, shape)
    assert areas.shape == (80,) and np.all(areas > 0)
    # measured relative error 1e-15 on seed 0
    assert abs(areas.sum() / (shape[0] * shape[1]) - 1) < 1e-6


def test_regular_grid_areas():
    # 5 x 4 grid with spacing 20 x 25, the first node 6 px (rows) and 8 px (columns)
    # from the pixel-edge border at -0.5
    ys = 5.5 + 20.0 * np.arange(5)
    xs = 7.5 + 25.0 * np.arange(4)
    shape = (int(ys[-1] + 0.5 + 6), int(xs[-1] + 0.5 + 8))  # same margin on the far side
    pts = np.stack(np.meshgrid(ys, xs, indexing="ij"), -1).reshape(-1, 2)
    areas = voronoi_areas(pts, shape).reshape(5, 4)
    # cell extent: half the spacing towards a neighbour, the full margin towards a border
    hy = np.array([6 + 10, 20, 20, 20, 10 + 6], float)
    hx = np.array([8 + 12.5, 25, 25, 12.5 + 8], float)
    expected = hy[:, None] * hx[None, :]
    # measured max relative error 0 (exact up to rounding)
    assert np.abs(areas / expected - 1).max() < 1e-9
    assert abs(areas.sum() - shape[0] * shape[1]) < 1e-6 * shape[0] * shape[1]


@pytest.mark.parametrize("n", [1, 2])
def test_fewer_than_three_points_equal_shares(n):
    areas = voronoi_areas(np.array([[10.0, 10.0], [30.0, 40.0]])[:n], (50, 60))
    assert np.allclose(areas, 3000.0 / n, rtol=0, atol=1e-12)


def test_collinear_points_give_strips():
    # the mirrored copies make collinear points non-degenerate: the cells are strips
    # across the field, bounded halfway between the points (rows -0.5 .. 49.5, width 40)
    pts = np.column_stack([np.linspace(5, 45, 6), np.full(6, 20.0)])
    areas = voronoi_areas(pts, (50, 40))
    expected = 40.0 * np.array([9.5, 8, 8, 8, 8, 8.5])
    assert np.abs(areas - expected).max() < 1e-9  # measured 0
