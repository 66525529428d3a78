"""Areas of the Voronoi cells of bead positions, clipped to the image field.

Paper, Appendix C: the thin-plate-spline weights are the Voronoi cell areas, so that a
bead in a sparse region counts as much as the many beads of a dense one. The points are
mirrored across the four borders of the field: every original cell is then bounded,
and its edges on the border coincide with the border, so no explicit clipping is needed.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import QhullError, Voronoi


def _polygon_area(vertices: np.ndarray) -> float:
    """Area of a convex polygon from its vertices (any order around the centroid)."""
    c = vertices.mean(axis=0)
    ang = np.arctan2(vertices[:, 1] - c[1], vertices[:, 0] - c[0])
    v = vertices[np.argsort(ang)]
    x, y = v[:, 0], v[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def voronoi_areas(points, shape: tuple[int, int]) -> np.ndarray:
    """Voronoi cell areas of points in a rectangular field, in square pixels.

    Parameters
    ----------
    points : array_like of shape (M, 2)
        Positions (row, column) in pixels, inside the field.
    shape : tuple of int
        Image shape (rows, columns); the field is ``[-0.5, rows - 0.5] x
        [-0.5, columns - 0.5]`` (pixel edges).

    Returns
    -------
    ndarray of shape (M,)
        Cell areas; they sum to ``rows * columns``. With fewer than 3 points, or
        degenerate (collinear) points, equal shares of the field are returned.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    m = len(pts)
    total = float(shape[0] * shape[1])
    if m < 3:
        return np.full(m, total / max(m, 1))
    lo, hi = -0.5, np.array(shape, dtype=np.float64) - 0.5
    mirrored = [pts]
    for axis in (0, 1):
        for edge in (lo, hi[axis]):
            q = pts.copy()
            q[:, axis] = 2 * edge - q[:, axis]
            mirrored.append(q)
    try:
        vor = Voronoi(np.concatenate(mirrored))
    except QhullError:
        return np.full(m, total / m)
    areas = np.empty(m)
    for i in range(m):
        region = vor.regions[vor.point_region[i]]
        if -1 in region or len(region) < 3:
            return np.full(m, total / m)
        areas[i] = _polygon_area(vor.vertices[region])
    return areas
