"""Each image's coefficient fields with the family as their prior (empirical Bayes).

One image's thin-plate field follows its own beads only. With faint beads the noise of
a bead's coefficients can be many times their spread over the field (faint stacks of
``bench/bench_family_oracle.py``; bench/RESULTS.md), and each image's field then carries
mostly noise, while the family holds the same microscope under other conditions. A
two-level model pools them:

    c_kb = mu(z_kb) + delta_k(z_kb) + e_kb,

with ``c_kb`` the coefficients of bead ``b`` of image ``k`` at ``z_kb``, ``mu`` the
family's mean field (the mean over the images of their own thin-plate fields),
``delta_k`` the image's smooth departure from it and ``e_kb`` the noise.

1. ``delta_k`` is the weighted thin-plate spline of the residuals ``c_kb - mu(z_kb)``
   (:class:`~napari_psfspace.core.model.tps.ThinPlateSpline`, its smoothing chosen by
   leave-one-out as for one image).
2. Its noise: per column, the residual variance ``s^2 = sum r^2 / (n - dof)`` of that
   fit, and the mean variance of the fitted field ``v_k = s^2 dof / n`` (a linear
   smoother with ``dof`` effective degrees of freedom).
3. The spread of the departures over the family: ``tau^2 = mean(delta^2) - mean(v)``
   (method of moments, per column, clipped at 0).
4. Each image's field is ``mu + delta_k tau^2 / (tau^2 + v_k)``: its own departure where
   its beads determine it (bright or many beads: ``v_k << tau^2``, the image's own
   field), the family's mean where they do not (faint or few beads).

The paper's per-image thin-plate field is the special case ``tau^2 >> v_k``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..common.threads import map_threads
from ..model.tps import ThinPlateSpline
from ..model.voronoi import voronoi_areas
from .result import space_at

#: Fewest beads for an image's own field; below, the image's field is the family's mean
#: plus a constant (the mean departure of its beads, shrunk as a field's is).
MIN_BEADS_FIELD = 4


@dataclass
class Fields:
    """The fields of every image, at the grid's nodes and at its beads.

    Attributes
    ----------
    nodes : list of ndarray of shape (G, C)
        Each image's field at the nodes (the family's mean for an image without beads).
    beads : list of ndarray of shape (n_k, C)
        The same fields at each image's beads.
    shrink : ndarray of shape (K, C)
        ``tau^2 / (tau^2 + v_k)`` of each image and column (1: its own field; 0: the
        family's mean).
    tau2 : ndarray of shape (C,)
        The spread of the images' departures from the family's mean, per column (less
        their noise).
    """

    nodes: list
    beads: list
    shrink: np.ndarray
    tau2: np.ndarray

    def share(self) -> np.ndarray:
        """Each image's share of its own field, shape (K,): the shrink factors weighted
        by the columns' spread ``tau^2`` (1: its beads determine its departure from the
        family's mean; 0: they do not, the family's mean stands for it); where no
        column departs from the mean beyond the noise, the plain mean of the factors
        (all 0: the family's mean for every image)."""
        total = float(self.tau2.sum())
        if total <= 0:
            return self.shrink.mean(axis=1)
        return self.shrink @ self.tau2 / total


def _spline(centers, values, shape, weights) -> ThinPlateSpline:
    return ThinPlateSpline(centers, values, weights=weights,
                           scale=0.5 * float(np.hypot(*shape)))


def shrunk_fields(centers: list[np.ndarray], values: list[np.ndarray],
                  grid: tuple[np.ndarray, np.ndarray],
                  shape: tuple[int, int], *, factor: float | None = None) -> Fields:
    """Every image's field of its beads' values, with the family's mean as the prior.

    Parameters
    ----------
    centers : list of ndarray of shape (n_k, 2)
        Each image's bead positions (row, column), pixels.
    values : list of ndarray of shape (n_k, C)
        Their values (e.g. coefficients on a PSF basis).
    grid : (ndarray (gy,), ndarray (gx,))
        The coarse grid's node coordinates, pixels.
    shape : (int, int)
        Image shape, pixels.
    factor : float in [0, 1], optional
        One shrink for every image and column instead of the empirical Bayes
        ``tau^2 / (tau^2 + v_k)``: 0 gives every image the family's mean field, 1 its
        whole departure. For oracles and comparisons (``bench/bench_family_oracle.py
        --shrink-oracle``); ``tau2`` is still the estimate's.

    Returns
    -------
    Fields
    """
    if factor is not None and not (np.isfinite(factor) and 0.0 <= float(factor) <= 1.0):
        raise ValueError(f"`factor` must be None or a number in [0, 1], got {factor!r}")
    gy, gx = grid
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    n_c = next(v.shape[1] for v in values if len(v))
    rich = [k for k, c in enumerate(centers) if len(c) >= MIN_BEADS_FIELD]
    some = [k for k, c in enumerate(centers) if len(c)]
    areas = dict(zip(rich, map_threads(lambda k: voronoi_areas(centers[k], shape), rich),
                     strict=True))
    splines = dict(zip(rich, map_threads(
        lambda k: _spline(centers[k], values[k], shape, areas[k]), rich), strict=True))
    if rich:
        own = map_threads(lambda k: np.asarray(splines[k](nodes)).reshape(len(nodes), -1),
                          rich)
        mu = np.mean(own, axis=0)  # (G, C)
    else:  # no image holds a field: the mean of every bead, constant
        mu = np.tile(np.concatenate([values[k] for k in some]).mean(axis=0), (len(nodes), 1))
    mu_grid = mu.T.reshape(n_c, len(gy), len(gx))
    def departure(k):
        """Image ``k``'s departure from ``mu``: at its beads and the nodes, its noise."""
        at = space_at(mu_grid, grid, centers[k])  # (n, C)
        r = values[k] - at
        n = len(r)
        if k in rich:
            spline = splines[k].refit(r)  # (the same beads: the same factorisation)
            fit = np.asarray(spline(centers[k])).reshape(n, -1)
            dof = np.asarray(spline.effective_dof, dtype=np.float64).reshape(-1)
            at_nodes = np.asarray(spline(nodes)).reshape(len(nodes), -1)
        else:  # a constant departure: the mean of its beads' residuals
            fit = np.tile(r.mean(axis=0), (n, 1))
            dof = np.ones(n_c)
            at_nodes = np.tile(r.mean(axis=0), (len(nodes), 1))
        s2 = ((r - fit) ** 2).sum(axis=0) / np.maximum(n - dof, 1.0)
        if n <= 1:  # one bead: its noise cannot be measured; the family's mean
            s2 = np.full(n_c, np.inf)
        return at_nodes, (at, fit), s2 * dof / n

    got = dict(zip(some, map_threads(departure, some), strict=True))
    dev_nodes = {k: g[0] for k, g in got.items()}
    dev_beads = {k: g[1] for k, g in got.items()}
    var = {k: g[2] for k, g in got.items()}
    used = [k for k in some if np.all(np.isfinite(var[k]))]
    if used:
        spread = np.mean([(dev_nodes[k] ** 2).mean(axis=0) for k in used], axis=0)
        tau2 = np.maximum(spread - np.mean([var[k] for k in used], axis=0), 0.0)
    else:
        tau2 = np.zeros(n_c)
    out_nodes: list = [mu.copy() for _ in centers]
    out_beads: list = [np.zeros((0, n_c)) for _ in centers]
    shrink = np.zeros((len(centers), n_c))
    for k in some:
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(np.isfinite(var[k]), tau2 / np.maximum(tau2 + var[k], 1e-300), 0.0)
        if factor is not None:
            s = np.full(n_c, float(factor))
        shrink[k] = s
        at, fit = dev_beads[k]
        out_nodes[k] = mu + dev_nodes[k] * s
        out_beads[k] = at + fit * s
    return Fields(out_nodes, out_beads, shrink, tau2)
