"""Weighted smoothing thin-plate splines, the smoothing chosen by leave-one-out.

Paper, Appendix C, eq. (8): each PSF coefficient ``alpha_i`` is the minimiser of
``1/2 sum_m w_m |alpha(z_m) - beta_{i,m}|^2 + eta/2 |alpha|_{H^2}^2``, a thin-plate
spline found from an (M+3) x (M+3) linear system. The weights are Voronoi areas.

Implementation. With ``K`` the kernel matrix (``phi(r) = r^2 log r``), ``P = [1, y, x]``,
``Q2`` an orthonormal basis of ``null(P^T)`` and ``D = diag(1 / w)``, the spline
coefficients are ``c = Q2 (Q2^T (K + eta D) Q2)^{-1} Q2^T y``. One generalised
symmetric eigendecomposition ``Q2^T K Q2 V = Q2^T D Q2 V Lambda`` diagonalises the
system for every ``eta`` at once: the residuals at the beads and the leverages
``S_mm`` cost one matrix product per candidate ``eta``, so the exact leave-one-out error
``sum_m w_m (r_m / (1 - S_mm))^2`` is evaluated on a log grid. Each output column gets
its own ``eta``.

The fitted function is the one :class:`scipy.interpolate.RBFInterpolator` gives with
``kernel="thin_plate_spline"``, ``degree=1`` and ``smoothing = eta / w_m`` in the scaled
coordinates (``tests/test_tps.py`` checks it): that solves one system per smoothing
value, where the eigendecomposition here scores the whole grid of values, for every
column, from one factorisation.
"""

from __future__ import annotations

import copy

import numpy as np
from scipy import linalg

from ..common.progress import check_halt


def _tps_kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Thin-plate kernel ``r^2 log r`` between two point sets, shape (len(a), len(b))."""
    d2 = (a[:, 0, None] - b[None, :, 0]) ** 2
    d2 += (a[:, 1, None] - b[None, :, 1]) ** 2
    k = np.zeros_like(d2)
    np.log(d2, out=k, where=d2 > 0)  # (0 at r = 0, the kernel's limit)
    k *= d2
    k *= 0.5
    return k


def _bin_samples(pts: np.ndarray, vals: np.ndarray, w: np.ndarray, max_nodes: int):
    """Weighted means of the samples in the non-empty cells of a grid of <= max_nodes.

    Returns
    -------
    nodes (n, 2), node_values (n, K), node_weights (n,), cell (M,) (node of each
    sample), share (M,) (each sample's weight / its node's weight)
    """
    g = max(2, int(np.floor(np.sqrt(max_nodes))))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    idx = np.minimum((g * (pts - lo) / span).astype(int), g - 1)
    _, cell = np.unique(idx[:, 0] * g + idx[:, 1], return_inverse=True)
    n = int(cell.max()) + 1
    wsum = np.bincount(cell, weights=w, minlength=n)
    nodes = _cell_means(pts, w, cell, wsum)
    return nodes, _cell_means(vals, w, cell, wsum), wsum, cell, w / wsum[cell]


def _cell_means(vals: np.ndarray, w: np.ndarray, cell: np.ndarray,
                wsum: np.ndarray) -> np.ndarray:
    """Weighted means (n, K) of the samples' values (M, K) in each cell."""
    return np.column_stack([np.bincount(cell, weights=w * vals[:, j], minlength=len(wsum))
                            for j in range(vals.shape[1])]) / wsum[:, None]


#: A field richer than ``max_dof`` must lower the leave-one-out error by this many
#: standard errors of the paired per-sample difference (:class:`ThinPlateSpline`).
RICHER_Z = 2.0

#: Values (samples x columns x smoothing values) the smoothing's selection holds at once:
#: bounds the memory of scoring a block of the grid in one matrix product.
SELECT_BLOCK = 1 << 20


class ThinPlateSpline:
    """Smoothing thin-plate spline in 2-D, vector-valued, weighted, tuned by leave-one-out.

    Parameters
    ----------
    points : array_like of shape (M, 2)
        Sample positions (row, column) in pixels.
    values : array_like of shape (M,) or (M, K)
        Sample values; each column is fitted independently.
    weights : array_like of shape (M,), optional
        Positive data weights ``w_m`` (e.g. Voronoi areas); normalised to mean 1, so
        ``eta`` is relative to the mean weight (refitting a subset with the same
        ``eta`` is a slightly different model unless the weights are rescaled).
    smoothing : float, sequence of float, or None
        ``eta`` per column (or one for all), in the normalised units below; ``None``
        picks each column's ``eta`` by the weighted leave-one-out error (each bead held
        out in turn, exact closed form ``r_m / (1 - S_mm)``).
    scale : float, optional
        Length (pixels) that maps to 1 in the internal coordinates; default the half
        diagonal of the points' bounding box. ``eta`` is relative to this scale.
    max_nodes : int or None
        Above this many samples the spline is fitted to weighted means of the samples in
        the cells of a grid (at most ``max_nodes`` nodes): the solves are O(M^3), and the
        coefficient maps are smooth. Leave-one-out residuals are then those of each
        sample with its share of its node's leverage. None: never.
    max_dof : float, "half" or None
        When ``eta`` is chosen by leave-one-out, at most this many effective degrees of
        freedom ("half": half the samples) unless the held-out samples show that a richer
        field predicts them better: the leave-one-out error at the unconstrained choice
        must beat the constrained one by :data:`RICHER_Z` standard errors of the paired
        per-sample difference (:attr:`richer`). A field that interpolates its samples
        (as many dof as beads) follows their noise. None: no limit.

    Attributes
    ----------
    smoothing : ndarray of shape (K,)
        The ``eta`` used for each column.
    score : ndarray of shape (K,)
        The selection score at the chosen ``eta`` (``nan`` when ``eta`` was given).
    effective_dof : ndarray of shape (K,)
        Trace of the influence matrix: 3 for an affine fit, M for interpolation.
    richer : ndarray of shape (K,), bool
        Columns whose field uses more than ``max_dof`` because the held-out samples showed
        it predicts better.
    loo_gain : ndarray of shape (K,)
        For those, the relative drop of the leave-one-out score it brought.
    """

    def __init__(self, points, values, *, weights=None, smoothing=None, scale=None,
                 max_nodes: int | None = 1000, max_dof: float | str | None = "half"):
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        vals = np.asarray(values, dtype=np.float64)
        self._vector = vals.ndim == 2
        vals = vals.reshape(len(pts), -1)
        m = len(pts)
        if m < 4:
            raise ValueError(f"A thin-plate spline needs at least 4 points, got {m}.")
        if not np.all(np.isfinite(vals)):
            raise ValueError("`values` contains NaN or infinite entries.")
        w = np.ones(m) if weights is None else np.asarray(weights, dtype=np.float64)
        if w.shape != (m,) or np.any(~np.isfinite(w)) or np.any(w <= 0):
            raise ValueError(f"`weights` must be {m} positive finite numbers.")
        w = w / w.mean()
        if scale is None:
            scale = 0.5 * float(np.hypot(*(pts.max(axis=0) - pts.min(axis=0))))
        binned = None
        if max_nodes is not None and m > max_nodes:
            # the solves are O(M^3): beyond max_nodes, fit weighted means of the samples in
            # the cells of a grid (smooth maps lose nothing: tested)
            binned = (pts, vals, w, *_bin_samples(pts, vals, w, max_nodes))
            pts, vals, w = binned[3], binned[4], binned[5]
            w = w / w.mean()
            m = len(pts)
        self.n_nodes = m
        self.max_dof = (max(3.0, 0.5 * m) if max_dof == "half" else
                        None if max_dof is None else float(max_dof))
        self._center = pts.mean(axis=0)
        self._scale = scale if scale > 0 else 1.0
        z = (pts - self._center) / self._scale
        self._nodes = z
        poly = np.column_stack([np.ones(m), z])
        q, rmat = np.linalg.qr(poly, mode="complete")
        if np.linalg.matrix_rank(poly) < 3:
            raise ValueError("The points are collinear: a thin-plate spline is undefined.")
        q1, q2 = q[:, :3], q[:, 3:]
        kmat = _tps_kernel(z, z)
        dinv = 1.0 / w
        kt = q2.T @ kmat @ q2
        bt = q2.T @ (dinv[:, None] * q2)
        lam, vec = linalg.eigh(0.5 * (kt + kt.T), 0.5 * (bt + bt.T))
        lam = np.maximum(lam, 1e-12 * max(float(lam.max()), 1e-300))
        self._factors = (q1, q2, rmat, kmat, dinv, w, lam, vec)
        self._binned = binned
        self._fit(vals, smoothing)

    def refit(self, values, *, smoothing=None) -> ThinPlateSpline:
        """The spline of the same points, weights and scale fitted to other values.

        Reuses this spline's factorisation (kernel matrix and eigendecomposition): the
        cost of a fit is then that of choosing ``eta``.

        Parameters
        ----------
        values : array_like of shape (M,) or (M, K)
            New sample values at this spline's points.
        smoothing
            As for :class:`ThinPlateSpline`.

        Returns
        -------
        ThinPlateSpline
        """
        vals = np.asarray(values, dtype=np.float64)
        m = len(self._binned[0]) if self._binned is not None else self.n_nodes
        if vals.ndim not in (1, 2) or len(vals) != m:
            raise ValueError(f"`values` must have {m} rows (one per point), got shape "
                             f"{vals.shape}.")
        if not np.all(np.isfinite(vals)):
            raise ValueError("`values` contains NaN or infinite entries.")
        new = copy.copy(self)
        new._vector = vals.ndim == 2
        vals = vals.reshape(m, -1)
        if self._binned is not None:
            p0, _, w0, nodes, _, wsum, cell, share = self._binned
            node_vals = _cell_means(vals, w0, cell, wsum)
            new._binned = (p0, vals, w0, nodes, node_vals, wsum, cell, share)
            vals = node_vals
        new._fit(vals, smoothing)
        return new

    def _fit(self, vals, smoothing) -> None:
        """Coefficients, residuals and leverages of ``vals`` (M, K) on the factors."""
        check_halt()
        q1, q2, rmat, kmat, dinv, w, lam, vec = self._factors
        m = len(q2)
        proj = vec.T @ (q2.T @ vals)  # (M-3, K)
        n_col = vals.shape[1]
        self.richer = np.zeros(n_col, bool)
        self.loo_gain = np.zeros(n_col)
        if smoothing is None:
            etas, scores = self._select(lam, vec, q2, proj, dinv, w)
        else:
            etas = np.broadcast_to(np.asarray(smoothing, dtype=np.float64), (n_col,)).copy()
            if np.any(~np.isfinite(etas)) or np.any(etas < 0):
                raise ValueError(f"`smoothing` must be >= 0, got {smoothing!r}.")
            scores = np.full(n_col, np.nan)
        coef = np.empty((m, n_col))
        for j in range(n_col):
            coef[:, j] = q2 @ (vec @ (proj[:, j] / (lam + etas[j])))
        resid = etas[None, :] * dinv[:, None] * coef
        fitted = vals - resid
        poly_coef = linalg.solve_triangular(rmat[:3], q1.T @ (fitted - kmat @ coef))
        self._coef, self._poly = coef, poly_coef
        # leverage: diag(I - S) = eta * D_mm * sum_k U_mk^2 / (Lambda_k + eta), U = Q2 V
        u2 = (q2 @ vec) ** 2
        self._one_minus_leverage = np.column_stack(
            [e * dinv * (u2 @ (1.0 / (lam + e))) for e in etas]
        )
        self.smoothing, self.score = etas, scores
        self.effective_dof = np.array(
            [m - float(np.sum(e / (lam + e))) if e > 0 else float(m) for e in etas]
        )
        self.residuals = resid
        if self._binned is not None:
            # per sample: in-sample residual, and its share of its node's leverage
            p0, v0, w0, _, _, _, cell, share = self._binned
            self.residuals = v0 - self._evaluate(p0)
            node_lev = 1.0 - self._one_minus_leverage  # (nodes, K)
            self._one_minus_leverage = 1.0 - node_lev[cell] * share[:, None]

    @property
    def standardized_residuals(self) -> np.ndarray:
        """In-sample residuals over ``sqrt(1 - S_mm)``, shape (M, K): of one variance at
        every sample for noise of one variance, so that a sample the fit bends to (an
        isolated one, high leverage) shows its misfit. Zero where the spline interpolates.
        """
        denom = self._one_minus_leverage
        out = np.zeros_like(self.residuals)
        ok = denom > 1e-12
        out[ok] = self.residuals[ok] / np.sqrt(denom[ok])
        return out if self._vector else out[:, 0]

    @property
    def loo_residuals(self) -> np.ndarray:
        """Leave-one-out residuals ``y_m - f_{-m}(z_m)`` at the samples, shape (M, K).

        Exact for a linear smoother: the in-sample residual divided by ``1 - S_mm``.
        Zero where the spline interpolates (``eta = 0``).
        """
        denom = self._one_minus_leverage
        out = np.zeros_like(self.residuals)
        ok = denom > 1e-12
        out[ok] = self.residuals[ok] / denom[ok]
        return out if self._vector else out[:, 0]

    def _select(self, lam, vec, q2, proj, dinv, w):
        """Per-column eta minimising the weighted leave-one-out error on a log grid, with
        at most :attr:`max_dof` effective degrees of freedom unless the held-out samples
        show that more predict better (:data:`RICHER_Z` standard errors of the paired
        per-sample difference of the LOO errors; ``self.richer`` records where)."""
        m = q2.shape[0]
        top = max(float(lam.max()), 1e-12)
        grid = top * np.logspace(-9, 3, 97)
        n_col = proj.shape[1]
        basis = q2 @ vec  # (M, M-3)
        u2 = basis**2
        scores = np.empty((len(grid), n_col))
        # sum_k eta / (Lambda_k + eta) per value: m minus the effective degrees of freedom
        shrink = np.sum(grid[:, None] / (lam[None, :] + grid[:, None]), axis=1)
        dof = m - shrink

        def loo_at(eta):
            resid = eta * dinv[:, None] * (basis @ (proj / (lam + eta)[:, None]))
            one_minus_lev = eta * dinv * (u2 @ (1.0 / (lam + eta)))  # diag(I - S)
            return resid, resid / np.maximum(one_minus_lev, 1e-12)[:, None]

        # every smoothing value of the grid at once, a block of them per matrix product
        # (one product of the basis with many columns, not one per value)
        step = max(1, int(SELECT_BLOCK // max(m * n_col, 1)))
        for start in range(0, len(grid), step):
            check_halt()
            etas = grid[start:start + step]  # (B,)
            inv = 1.0 / (lam[None, :] + etas[:, None])  # (B, M-3)
            scaled = (proj[:, None, :] * inv.T[:, :, None]).reshape(len(lam), -1)
            resid = (etas[:, None, None] * dinv[None, :, None]
                     * np.moveaxis((basis @ scaled).reshape(m, len(etas), n_col), 1, 0))
            lev = etas[:, None] * dinv[None, :] * (inv @ u2.T)  # (B, M): diag(I - S)
            loo = resid / np.maximum(lev, 1e-12)[:, :, None]
            scores[start:start + step] = (w[None, :, None] * loo**2).sum(axis=1) / m
        best = np.argmin(scores, axis=0)
        self.richer = np.zeros(n_col, bool)
        self.loo_gain = np.zeros(n_col)
        cap = self.max_dof
        if cap is not None and (dof <= cap).any():
            allowed = np.flatnonzero(dof <= cap)
            for j in range(n_col):
                if dof[best[j]] <= cap:
                    continue
                g_cap = allowed[np.argmin(scores[allowed, j])]
                _, loo_u = loo_at(grid[best[j]])
                _, loo_c = loo_at(grid[g_cap])
                diff = w * (loo_c[:, j] ** 2 - loo_u[:, j] ** 2)
                se = float(diff.std(ddof=1)) / np.sqrt(m) if m > 1 else np.inf
                gain = float(diff.mean())
                if gain > RICHER_Z * se and gain > 0:
                    self.richer[j] = True
                    self.loo_gain[j] = gain / max(float(scores[g_cap, j]), 1e-300)
                else:
                    best[j] = g_cap
        return grid[best], scores[best, np.arange(n_col)]

    def __call__(self, points) -> np.ndarray:
        """Evaluate the spline at positions (row, column) in pixels, shape (N, 2).

        Returns
        -------
        ndarray of shape (N, K), or (N,) if the spline was fitted to a 1-D array.
        """
        out = self._evaluate(points)
        return out if self._vector else out[:, 0]

    def _evaluate(self, points) -> np.ndarray:
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        z = (pts - self._center) / self._scale
        out = np.empty((len(z), self._coef.shape[1]))
        for start in range(0, len(z), 4096):  # bounded memory on large grids
            zz = z[start:start + 4096]
            out[start:start + 4096] = (
                _tps_kernel(zz, self._nodes) @ self._coef
                + np.column_stack([np.ones(len(zz)), zz]) @ self._poly
            )
        return out
