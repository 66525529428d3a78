"""An image's few coordinates in its family, from a few of its beads.

A family's operators vary with a few conditions (:mod:`.dimensions`): an image's
coefficient field is modelled as

    F(x) = m(x) + sum_l z_l d_l(x) + R(x),

with ``m`` the family's mean field, ``d_l`` its ``L`` principal directions (coordinate
``z_l`` of prior variance ``v_l``) and ``R`` the family's miss, a Gaussian field of
coefficient covariance ``C_R`` and spatial correlation ``exp(-d^2 / 2 ell^2)``.

Each clicked bead ``p`` at ``x_p`` gives its coefficients ``c_p = g_p F(x_p) + e_p`` on
the family's PSF basis (``g_p`` its amplitude against the family's unit flux, ``e_p`` its
noise, white in the PSF's pixels: covariance ``sd_p^2 Gram^-1`` on the coefficients).
:func:`fit_coordinates` finds ``z`` (the posterior mean given the noise, ``L`` unknowns)
and the amplitudes by alternating exact least squares; :func:`krige_miss` then adds the
part of the beads' residuals that the miss's covariance carries to the rest of the field
(near the beads only: the miss's correlation length is short), the freedom beyond the
family used only as far as the beads determine it; :func:`spread_at` is the posterior
standard deviation of the PSF.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..model.psf_field import interp_weights

#: Share of each side of the field left out of its central part (:attr:`Model.central`):
#: the PSF error over the field is judged inside, at the centres of a 4 x 4 grid of
#: cells and between them.
MARGIN = 0.125
#: Most beads the miss is kriged from (a subset spread over the field beyond): its
#: correlation is short, and more beads add only cost.
MAX_KRIGED = 40


def bilinear(grid, points: np.ndarray) -> np.ndarray:
    """Bilinear weights (P, G) of ``points`` (P, 2) on the nodes of ``grid`` (row-major),
    as the operator interpolates its PSFs between nodes."""
    gy, gx = grid
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    j0, j1, ty = interp_weights(gy, pts[:, 0])
    k0, k1, tx = interp_weights(gx, pts[:, 1])
    w = np.zeros((len(pts), len(gy) * len(gx)))
    rows = np.arange(len(pts))
    for j, wy in ((j0, 1 - ty), (j1, ty)):
        for k, wx in ((k0, 1 - tx), (k1, tx)):
            np.add.at(w, (rows, j * len(gx) + k), wy * wx)
    return w


@dataclass
class Model:
    """The few-dimensional model of a family's fields (built by :mod:`.dimensions`).

    Attributes
    ----------
    grid : (ndarray (gy,), ndarray (gx,))
        Node coordinates, pixels.
    shape : (int, int)
        Image shape, pixels.
    mean : ndarray of shape (G, I)
        ``m`` at the nodes (row-major).
    directions : ndarray of shape (L, G, I)
        ``d_l``, orthonormal over the nodes and coefficients.
    variances : ndarray of shape (L,)
        ``v_l``: the variance of each coordinate over the family's images.
    miss_cov : ndarray of shape (I, I)
        ``C_R``: the covariance of the family's miss at a node.
    miss_length : float
        ``ell``, pixels.
    gram : ndarray of shape (I, I)
        The PSF basis's Gram matrix (the PSF's norm is ``sqrt(c Gram c)``).
    miss_scale : ndarray of shape (G,), optional
        The miss's standard deviation at each node relative to its mean (larger at the
        rim, where the family's fields are extrapolated from their beads): the miss at
        ``x`` is ``s(x) R(x)``, ``s`` bilinear between the nodes. None: 1 everywhere.
    """

    grid: tuple[np.ndarray, np.ndarray]
    shape: tuple[int, int]
    mean: np.ndarray
    directions: np.ndarray
    variances: np.ndarray
    miss_cov: np.ndarray
    miss_length: float
    gram: np.ndarray
    miss_scale: np.ndarray | None = None

    @property
    def n_directions(self) -> int:
        """``L``."""
        return int(len(self.directions))

    @property
    def nodes(self) -> np.ndarray:
        """The nodes (G, 2), pixels, row-major."""
        gy, gx = self.grid
        return np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)

    @property
    def central(self) -> np.ndarray:
        """Which nodes (G,) lie in the field's central part, :data:`MARGIN` of each side
        left out: where beads are found and an operator is judged (its rim is
        extrapolated from the beads inside)."""
        rel = self.nodes / np.maximum(np.asarray(self.shape, np.float64) - 1, 1)
        return np.all((rel >= MARGIN) & (rel <= 1 - MARGIN), axis=1)

    def scale_at(self, points: np.ndarray) -> np.ndarray:
        """The miss's relative standard deviation :attr:`miss_scale` at ``points``
        (P, 2), bilinear between the nodes, (P,)."""
        pts = np.asarray(points, np.float64).reshape(-1, 2)
        if self.miss_scale is None:
            return np.ones(len(pts))
        return bilinear(self.grid, pts) @ self.miss_scale

    def miss_var(self, points: np.ndarray) -> np.ndarray:
        """The miss's prior variance at ``points`` (P, 2) in the PSF's squared l2 norm,
        (P,)."""
        return self.scale_at(points) ** 2 * float(np.trace(self.gram @ self.miss_cov))

    def field(self, z: np.ndarray) -> np.ndarray:
        """``m + sum_l z_l d_l`` at the nodes (G, I)."""
        z = np.asarray(z, np.float64).reshape(-1)
        return self.mean + np.tensordot(z, self.directions[:len(z)], axes=1)


@dataclass
class CoordinateFit:
    """The coordinates of an image given its beads (:func:`fit_coordinates`).

    Attributes
    ----------
    z : ndarray of shape (L,)
        Posterior mean of the coordinates.
    cov : ndarray of shape (L, L)
        Their posterior covariance given the beads' noise.
    amplitudes : ndarray of shape (P,)
        ``g_p``.
    fitted : ndarray of shape (P, I)
        ``m + sum_l z_l d_l`` at the beads (without the amplitudes).
    residuals : ndarray of shape (P, I)
        ``c_p / g_p - fitted_p``.
    noise : ndarray of shape (P,)
        Per-pixel noise of each bead's PSF at unit amplitude: ``sd_p / g_p``.
    centers : ndarray of shape (P, 2)
    """

    z: np.ndarray
    cov: np.ndarray
    amplitudes: np.ndarray
    fitted: np.ndarray
    residuals: np.ndarray
    noise: np.ndarray
    centers: np.ndarray


def whitener(gram: np.ndarray) -> np.ndarray:
    """``W`` (upper triangular) with ``W^T W = Gram``: coefficients times ``W^T`` have
    the PSF's l2 norm."""
    return np.linalg.cholesky(gram + 1e-12 * np.trace(gram) / len(gram) * np.eye(len(gram))).T


def design(model: Model, centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model at beads (P, 2): the mean ``m(x_p)`` (P, I) and the directions
    ``d_l(x_p)`` (P, I, L), bilinear between the nodes."""
    w = bilinear(model.grid, centers)  # (P, G)
    return w @ model.mean, np.einsum("pg,lgi->pil", w, model.directions)


def fit_coordinates(model: Model, c: np.ndarray, sd: np.ndarray, centers: np.ndarray, *,
                    n_directions: int | None = None,
                    amplitude_range: tuple[float, float] = (0.5, 2.0),
                    n_iter: int = 50, at_beads: tuple | None = None) -> CoordinateFit:
    """The image's coordinates and its beads' amplitudes from the beads.

    Parameters
    ----------
    model : Model
    c : ndarray of shape (P, I)
        The beads' coefficients on the family's PSF basis (least squares, sum-1 patches).
    sd : ndarray of shape (P,)
        Per-pixel noise of each bead's sum-1 patch.
    centers : ndarray of shape (P, 2)
        Their positions (row, column), pixels.
    n_directions : int, optional
        ``L`` (at most the model's); default the model's.
    amplitude_range : (float, float)
        Range of each bead's amplitude ``g_p``.
    n_iter : int
        Alternations between the coordinates and the amplitudes at most (they stop once
        neither changes by more than ``1e-10`` relatively).
    at_beads : (ndarray, ndarray), optional
        :func:`design` at ``centers``, when already computed.

    Returns
    -------
    CoordinateFit
    """
    c = np.asarray(c, np.float64)
    n_p, n_i = c.shape
    centers = np.asarray(centers, np.float64).reshape(n_p, 2)
    sd = np.asarray(sd, np.float64).reshape(n_p)
    good = np.isfinite(sd) & (sd > 0)
    sd = np.where(good, sd, np.median(sd[good]) if good.any() else 1.0)
    n_l = model.n_directions if n_directions is None else min(int(n_directions),
                                                               model.n_directions)
    base, a = design(model, centers) if at_beads is None else at_beads
    a = a[:, :, :n_l]
    cw, bw, aw = whitened(model.gram, c, base, a)
    z, g, cov = solve_coordinates(cw, bw, aw, sd, model.variances[:n_l],
                                  amplitude_range=amplitude_range, n_iter=n_iter)
    fitted = base + a @ z if n_l else base
    return CoordinateFit(z, cov, g, fitted, c / g[:, None] - fitted, sd / g, centers)


def whitened(gram: np.ndarray, c: np.ndarray, base: np.ndarray, a: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The beads' coefficients (P, I), the mean (P, I) and the directions (P, I, L) at
    them, whitened by the basis's Gram matrix (their l2 norm is the PSF's)."""
    white = whitener(gram)
    return c @ white.T, base @ white.T, np.einsum("ji,pil->pjl", white, a)


def solve_coordinates(cw: np.ndarray, bw: np.ndarray, aw: np.ndarray, sd: np.ndarray,
                      variances: np.ndarray, *,
                      amplitude_range: tuple[float, float] = (0.5, 2.0), n_iter: int = 50
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fit_coordinates` on whitened arrays (:func:`whitened`): the coordinates
    (L,), the amplitudes (P,) and the coordinates' posterior covariance (L, L), by
    alternating exact least squares (at most ``n_iter`` alternations; they stop once
    neither changes by more than ``1e-10`` relatively)."""
    n_p, n_l = len(cw), aw.shape[2]
    prec = np.diag(1.0 / np.maximum(variances, 1e-300))
    lo, hi = amplitude_range
    g = np.ones(n_p)
    z = np.zeros(n_l)
    lhs = prec
    for _ in range(int(n_iter)):
        if n_l:
            q = g / sd  # each bead's rows scaled by g_p / sd_p
            ap = (aw * q[:, None, None]).reshape(-1, n_l)
            yp = ((cw - g[:, None] * bw) / sd[:, None]).reshape(-1)
            lhs = ap.T @ ap + prec
            z_new = np.linalg.solve(lhs, ap.T @ yp)
            fit = bw + aw @ z_new
        else:
            z_new, fit = z, bw
        mm = (fit * fit).sum(axis=1)
        g_new = np.where(mm > 0, (fit * cw).sum(axis=1) / np.maximum(mm, 1e-300),
                         1.0).clip(lo, hi)
        change = max(float(np.max(np.abs(z_new - z), initial=0.0))
                     / max(float(np.max(np.abs(z_new), initial=0.0)), 1e-300),
                     float(np.max(np.abs(g_new - g) / g_new)))
        z, g = z_new, g_new
        if change <= 1e-10:
            break
    return z, g, (np.linalg.inv(lhs) if n_l else np.zeros((0, 0)))


def solve_nested(cw: np.ndarray, bw: np.ndarray, aw: np.ndarray, sd: np.ndarray,
                 variances: np.ndarray, masks: np.ndarray, *,
                 amplitude_range: tuple[float, float] = (0.5, 2.0), n_iter: int = 50
                 ) -> np.ndarray:
    """:func:`solve_coordinates` of several models that use subsets of the same
    directions, all at once: the coordinates (S, L), zero outside each model's columns.

    ``masks`` (S, L) bool: the directions of each model. A direction left out gets a unit
    precision and no data, so its coordinate is exactly 0 and the others' normal
    equations are those of the model without it; each model's alternations stop as
    :func:`solve_coordinates`' do, its coordinates kept from then on."""
    masks = np.asarray(masks, bool)
    n_s, n_l = masks.shape
    n_p = len(cw)
    lo, hi = amplitude_range
    prec = np.where(masks, 1.0 / np.maximum(np.asarray(variances, np.float64), 1e-300), 1.0)
    eye = np.eye(n_l)
    g = np.ones((n_s, n_p))
    z = np.zeros((n_s, n_l))
    active = np.ones(n_s, bool)
    flat_a = aw.reshape(-1, n_l)  # (P I, L)
    for _ in range(int(n_iter)):
        s = np.flatnonzero(active)
        q = np.repeat(g[s] / sd, aw.shape[1], axis=1)  # (S', P I): each row's g_p / sd_p
        ap = q[:, :, None] * flat_a[None] * masks[s, None, :]
        yp = ((cw[None] - g[s, :, None] * bw[None]) / sd[None, :, None]).reshape(len(s), -1)
        lhs = np.einsum("sra,srb->sab", ap, ap) + prec[s, :, None] * eye
        z_new = np.linalg.solve(lhs, np.einsum("sra,sr->sa", ap, yp)[..., None])[..., 0]
        fit = bw[None] + np.einsum("pil,sl->spi", aw, z_new)
        mm = (fit * fit).sum(axis=2)
        g_new = np.where(mm > 0, (fit * cw[None]).sum(axis=2) / np.maximum(mm, 1e-300),
                         1.0).clip(lo, hi)
        change = np.maximum(np.abs(z_new - z[s]).max(axis=1, initial=0.0)
                            / np.maximum(np.abs(z_new).max(axis=1, initial=0.0), 1e-300),
                            (np.abs(g_new - g[s]) / g_new).max(axis=1))
        z[s], g[s] = z_new, g_new
        active[s[change <= 1e-10]] = False
        if not active.any():
            break
    return z


def relative_field_errors(fields: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """:func:`relative_field_error` of each of fields (S, G, I) against ``truth`` (G, I),
    whitened coefficients: (S,), the rms over the nodes where both PSFs are non-zero of
    their difference at unit l2 norm (NaN where there is no such node)."""
    f, t = np.asarray(fields, np.float64), np.asarray(truth, np.float64)
    fn, tn = np.linalg.norm(f, axis=2), np.linalg.norm(t, axis=1)
    ok = (fn > 0) & (tn > 0)[None]
    d = (f / np.where(ok, fn, 1.0)[..., None]
         - t[None] / np.where(tn > 0, tn, 1.0)[None, :, None])
    sq = np.where(ok, (d * d).sum(axis=2), 0.0).sum(axis=1)
    n = ok.sum(axis=1)
    return np.where(n > 0, np.sqrt(sq / np.maximum(n, 1)), np.nan)


def spread_subset(centers: np.ndarray, n: int) -> np.ndarray:
    """Indices of at most ``n`` of ``centers`` (P, 2) spread over the field: farthest
    points, from the one nearest their mean."""
    pts = np.asarray(centers, np.float64).reshape(-1, 2)
    if len(pts) <= n:
        return np.arange(len(pts))
    picks = [int(np.argmin(np.hypot(*(pts - pts.mean(axis=0)).T)))]
    d = np.hypot(*(pts - pts[picks[0]]).T)
    while len(picks) < n:
        nxt = int(np.argmax(d))
        picks.append(nxt)
        d = np.minimum(d, np.hypot(*(pts - pts[nxt]).T))
    return np.sort(np.array(picks))


def _kernel(model: Model, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The miss's spatial covariance factor between positions (P, 2) and (Q, 2),
    (P, Q): its correlation times its relative standard deviation at each end."""
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=-1)
    corr = np.exp(-0.5 * d2 / max(model.miss_length, 1e-9) ** 2)
    return corr * np.outer(model.scale_at(a), model.scale_at(b))


def _miss_factor(model: Model, fit: CoordinateFit):
    """Cholesky factor of the beads' residual covariance: the miss's plus the noise's
    (``sd^2 Gram^-1`` on each bead's coefficients)."""
    n_p, n_i = fit.residuals.shape
    inv_gram = np.linalg.inv(model.gram)
    cov = np.kron(_kernel(model, fit.centers, fit.centers), model.miss_cov)
    cov += np.kron(np.diag(fit.noise ** 2), inv_gram)
    return cho_factor(cov + 1e-15 * np.trace(cov) / len(cov) * np.eye(len(cov)), lower=True)


def krige_miss(model: Model, fit: CoordinateFit, points: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The miss at ``points`` (Q, 2) given the beads' residuals: its posterior mean
    (Q, I) and the posterior variance of the PSF it adds (Q,), in the PSF's squared l2
    norm.

    The miss's covariance is separable (``k(x, x') C_R``), so the variance removed at a
    point ``q`` is ``k_q^T M k_q`` with ``M[p, p'] = trace(C_R Gram C_R S^-1[p, p'])``,
    ``S`` the beads' residual covariance: one small matrix for every point.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    n_i = model.mean.shape[1]
    prior = model.miss_var(pts)
    n_p = len(fit.residuals)
    if not n_p or not np.any(prior > 0):
        return np.zeros((len(pts), n_i)), np.clip(prior, 0.0, None)
    if n_p > MAX_KRIGED:
        keep = spread_subset(fit.centers, MAX_KRIGED)
        fit = CoordinateFit(fit.z, fit.cov, fit.amplitudes[keep], fit.fitted[keep],
                            fit.residuals[keep], fit.noise[keep], fit.centers[keep])
        n_p = MAX_KRIGED
    factor = _miss_factor(model, fit)
    k = _kernel(model, pts, fit.centers)  # (Q, P)
    alpha = cho_solve(factor, fit.residuals.reshape(-1)).reshape(n_p, n_i)
    mean = k @ alpha @ model.miss_cov.T
    s_inv = cho_solve(factor, np.eye(n_p * n_i)).reshape(n_p, n_i, n_p, n_i)
    cgc = model.miss_cov @ model.gram @ model.miss_cov
    m = np.einsum("piqj,ji->pq", s_inv, cgc)
    reduction = np.einsum("qp,pr,qr->q", k, m, k)
    return mean, np.clip(prior - reduction, 0.0, None)


def spread_at(model: Model, fit: CoordinateFit, field: np.ndarray,
              miss_var: np.ndarray) -> np.ndarray:
    """Posterior standard deviation of the PSF at each node (G,), relative to its norm:
    the coordinates' uncertainty and the miss's, ``field`` (G, I) the posterior mean."""
    n_l = len(fit.z)
    var = np.asarray(miss_var, np.float64).copy()
    if n_l:
        d = model.directions[:n_l]  # (L, G, I)
        gd = np.einsum("ij,lgj->lgi", model.gram, d)
        var += np.einsum("lgi,lm,mgi->g", d, fit.cov, gd)
    norm = np.sqrt(np.einsum("gi,ij,gj->g", field, model.gram, field))
    return np.sqrt(np.clip(var, 0.0, None)) / np.maximum(norm, 1e-300)


def identify_field(model: Model, c: np.ndarray, sd: np.ndarray, centers: np.ndarray, *,
                   n_directions: int | None = None,
                   amplitude_range: tuple[float, float] = (0.5, 2.0), krige: bool = True,
                   spread: bool = True, at_beads: tuple | None = None, n_iter: int = 50,
                   fit: CoordinateFit | None = None
                   ) -> tuple[np.ndarray, np.ndarray | None, CoordinateFit]:
    """The image's field at the nodes (G, I), its relative spread (G,; None without
    ``spread``), and the fit (:func:`fit_coordinates`, unless given as ``fit``;
    ``krige``: with the miss)."""
    if fit is None:
        fit = fit_coordinates(model, c, sd, centers, n_directions=n_directions,
                              amplitude_range=amplitude_range, at_beads=at_beads,
                              n_iter=n_iter)
    field = model.field(fit.z)
    if krige:
        add, miss_var = krige_miss(model, fit, model.nodes)
        field = field + add
    elif not spread:
        return field, None, fit
    else:
        miss_var = model.miss_var(model.nodes)
    return field, spread_at(model, fit, field, miss_var) if spread else None, fit


def relative_field_error(field: np.ndarray, truth: np.ndarray,
                         gram: np.ndarray | None = None,
                         where: np.ndarray | None = None) -> float:
    """The rms over the nodes (``where``: those, (G,) bool) of the PSF's error, each PSF
    of ``field`` and of ``truth`` (G, I) scaled to unit l2 norm first (a field's
    amplitude is not its PSF's); ``gram`` the basis's Gram matrix (None: an orthonormal
    basis, or whitened coefficients)."""
    f, t = np.asarray(field, np.float64), np.asarray(truth, np.float64)
    if where is not None:
        f, t = f[where], t[where]
    if gram is not None:
        white = whitener(np.asarray(gram, np.float64))
        f, t = f @ white.T, t @ white.T
    return float(relative_field_errors(f[None], t)[0])
