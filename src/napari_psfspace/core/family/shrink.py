"""Each image's coefficient fields with the family as their prior (empirical Bayes).

One image's thin-plate field follows its own beads only. With faint beads the noise of
a bead's coefficients can be many times their spread over the field (faint stacks of
``bench/bench_family_oracle.py``), and each image's field then carries
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

Faint beads' values have heavy tails: a bead whose background fit took most of its flux
is normalised by a small sum, and its values are then many times as noisy as its
neighbours'. Each image's own field is therefore refitted: a bead whose standardized
residual about the fit is beyond :data:`ROBUST_SCALE` robust standard deviations keeps a
weight that caps its share of it (:func:`bead_weights`; at most :data:`ROBUST_PASSES`
refits), and the departure and its noise are those of the weighted fit.
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
#: Robust standard deviations (the standardized residuals' rms over the columns, each
#: column scaled by its median absolute deviation over the image's beads) beyond which a
#: bead's weight in its image's field is capped (:func:`bead_weights`). Gaussian noise
#: passes 2 with probability exp(-4) on 2 columns and about 1e-4 on 8 (the family's
#: fields have 2 I columns); 3 gave nearly the same fields on the faint stacks it was
#: set on.
ROBUST_SCALE = 2.0
#: Refits of an image's field with the robust weights, at most.
ROBUST_PASSES = 3
#: No further refit once no bead's robust weight changes by this much.
ROBUST_TOL = 0.05
#: Fewest beads for the robust weights: below, the median absolute deviation of the
#: residuals says too little of their spread, and every bead keeps its weight.
MIN_BEADS_ROBUST = 8


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
    weights : list of ndarray of shape (n_k,), optional
        Each bead's robust weight in its image's field (:func:`bead_weights`; 1: as
        its Voronoi area alone).
    """

    nodes: list
    beads: list
    shrink: np.ndarray
    tau2: np.ndarray
    weights: list | None = None

    def relative_noise(self) -> np.ndarray:
        """Each image's field's posterior standard deviation from its beads' noise,
        relative to the field's mean norm over the nodes, shape (K,): per column the
        shrunk field's variance ``shrink v_k``, ``v_k = tau^2 (1 - shrink) / shrink``
        the noise of its own departure (0 where its beads determine it exactly)."""
        s = np.clip(self.shrink, 1e-12, 1.0)
        var = (s * self.tau2[None, :] * (1.0 - s) / s).sum(axis=1)
        norm = np.array([float(np.sqrt((n ** 2).sum(axis=1)).mean()) for n in self.nodes])
        return np.sqrt(var) / np.maximum(norm, 1e-300)

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


def bead_weights(residuals: np.ndarray, scale: float | None = None) -> np.ndarray:
    """Robust weights of beads from their residuals about a field.

    Each column is scaled by ``1.4826`` times its median absolute deviation (a column
    without spread is left out), and ``u`` is a bead's rms over the columns. A bead
    with ``u <= scale`` keeps weight 1; beyond, ``(scale / u)^2``, so that its weighted
    squared residual is no more than that of a bead at ``scale``.

    Parameters
    ----------
    residuals : ndarray of shape (n, C)
        The beads' residuals about a fit.
    scale : float, optional
        Robust standard deviations kept whole (default :data:`ROBUST_SCALE`).

    Returns
    -------
    ndarray of shape (n,), in (0, 1]
        All ones below :data:`MIN_BEADS_ROBUST` beads.
    """
    r = np.asarray(residuals, dtype=np.float64).reshape(len(residuals), -1)
    if len(r) < MIN_BEADS_ROBUST:
        return np.ones(len(r))
    mad = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
    spread = mad > 1e-12 * max(float(np.abs(r).max()), 1e-300)
    if not spread.any():
        return np.ones(len(r))
    u = np.sqrt(np.mean((r[:, spread] / mad[spread]) ** 2, axis=1))
    t = ROBUST_SCALE if scale is None else float(scale)
    return np.minimum(1.0, (t / np.maximum(u, 1e-300)) ** 2)


def _robust_spline(centers, values, shape, areas) -> tuple[ThinPlateSpline, np.ndarray]:
    """An image's own field with :func:`bead_weights` of its standardized residuals,
    iterated (at most :data:`ROBUST_PASSES` refits, none where no bead is down-weighted:
    a bead the first fit bends to shows its misfit once its weight is cut), and the
    weights."""
    fit = _spline(centers, values, shape, areas)
    w = np.ones(len(centers))
    for _ in range(ROBUST_PASSES):
        new = bead_weights(np.asarray(fit.standardized_residuals).reshape(len(centers), -1))
        if np.max(np.abs(new - w)) < ROBUST_TOL:
            break
        w = new
        fit = _spline(centers, values, shape, areas * w)
    return fit, w


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
    fitted = dict(zip(rich, map_threads(
        lambda k: _robust_spline(centers[k], values[k], shape, areas[k]), rich), strict=True))
    splines = {k: f[0] for k, f in fitted.items()}
    robust = {k: f[1] for k, f in fitted.items()}
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
        w = robust.get(k, np.ones(n))  # the field's robust weights (1: none)
        s2 = (w[:, None] * (r - fit) ** 2).sum(axis=0) / np.maximum(w.sum() - dof, 1.0)
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
    weights = [robust.get(k, np.ones(len(c))) for k, c in enumerate(centers)]
    return Fields(out_nodes, out_beads, shrink, tau2, weights)
