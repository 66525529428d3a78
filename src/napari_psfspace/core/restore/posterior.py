"""The family as a Gaussian prior over an image's PSF field; a few beads as its likelihood.

A family of operators (:class:`~napari_psfspace.core.family.OperatorFamily`) holds the
coefficient field ``F_k(x)`` (``I`` numbers at each node ``x`` of the coarse grid) of
each of ``K`` images. The field of a new image is modelled as a Gaussian process

    F(x) = m(x) + sum_k (w_k + v_k . sqrt(12) u) f_k(x) + D(x),

- ``m`` the family's mean field and ``f_k = (F_k - m) / sqrt(K - 1)`` its deviations:
  ``w ~ N(0, s^2)`` puts the image anywhere on the (continuous) span of the conditions
  learnt, beyond their range too; ``v ~ N(0, t^2)`` lets the mix vary over the field as
  a plane (a tilted focus puts each part of the field under another condition);
- ``D`` a field the family never showed: ``D ~ GP(0, C (t_a^2 k_a + t_s^2 k_s))``, with
  ``C`` (I, I) the family's covariance of the coefficients over conditions and nodes
  (plus a twentieth of its mean variance in every direction, so that no direction of
  the PSF basis is ruled out), ``k_a(u, v) = 1 + 12 u . v`` an affine field (a focus
  shift, a tilt of the slide) and ``k_s`` a squared-exponential field of length
  :data:`LENGTH` (coordinates ``u`` scaled to the image, -0.5 to 0.5).

Each clicked bead ``p`` gives its coefficients ``c_p = g_p F(x_p) + e_p``, ``e_p`` white
with the per-pixel noise of its sum-1 patch, ``g_p`` its amplitude. The scales
``s, t, t_a, t_s`` are those of highest evidence (type-II maximum likelihood): the beads
say how far the image lies from the family. The operator is the posterior mean field;
its spread (the posterior standard deviation of the PSF at each node, relative to the
PSF's norm) says where the beads leave it undetermined.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize

from ..model.psf_field import interp_weights

#: Length scale of the field the family never showed, in units of the image's side.
LENGTH = 0.5
#: Share of the coefficients' mean variance added in every direction of the PSF basis.
DIRECTION_FLOOR = 0.05
#: Bounds of the log10 of the scales relative to the family's own (span, affine, smooth).
LOG_BOUNDS = (-4.0, 1.5)


@dataclass
class FieldPrior:
    """A Gaussian prior over a coefficient field on a coarse grid.

    Attributes
    ----------
    grid : (ndarray (gy,), ndarray (gx,))
        Node coordinates, pixels.
    shape : (int, int)
        Image shape, pixels.
    mean : ndarray of shape (G, I)
        ``m`` at the nodes (row-major).
    span : ndarray of shape (K, G, I)
        ``f_k`` at the nodes.
    coef_cov : ndarray of shape (I, I)
        ``C``.
    """

    grid: tuple[np.ndarray, np.ndarray]
    shape: tuple[int, int]
    mean: np.ndarray
    span: np.ndarray
    coef_cov: np.ndarray

    @property
    def nodes(self) -> np.ndarray:
        """The nodes (G, 2), pixels, row-major."""
        gy, gx = self.grid
        return np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)

    def at(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean (P, I) and span (K, P, I) at ``points`` (P, 2), bilinear between nodes
        (as the operator's PSFs are)."""
        w = bilinear(self.grid, points)  # (P, G)
        return w @ self.mean, np.einsum("pg,kgi->kpi", w, self.span)

    def scaled(self, points: np.ndarray) -> np.ndarray:
        """Positions (P, 2) scaled to the image and centred: -0.5 to 0.5."""
        return np.asarray(points, np.float64) / np.asarray(self.shape, np.float64) - 0.5


def bilinear(grid, points: np.ndarray) -> np.ndarray:
    """Bilinear weights (P, G) of ``points`` (P, 2) on the nodes of ``grid``."""
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


def family_prior(subspace) -> FieldPrior:
    """The Gaussian prior of a family's fields (:class:`FieldPrior`)."""
    space = subspace.space.reshape(subspace.n_space, -1).T  # (G, J)
    fields = np.einsum("gj,kij->kgi", space, subspace.gammas)  # (K, G, I)
    mean = fields.mean(axis=0)
    dev = fields - mean
    k = len(fields)
    span = dev / np.sqrt(max(k - 1, 1))
    flat = dev.reshape(-1, dev.shape[-1])
    cov = flat.T @ flat / max(len(flat), 1)
    floor = DIRECTION_FLOOR * max(float(np.trace(cov)) / len(cov), 1e-30)
    return FieldPrior(subspace.grid, tuple(subspace.shape), mean, span,
                      cov + floor * np.eye(len(cov)))


def spatial_kernels(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The affine and the smooth kernel between scaled positions ``u`` (P, 2) and ``v``
    (Q, 2), each (P, Q)."""
    affine = 1.0 + 12.0 * (u @ v.T)
    d2 = ((u[:, None, :] - v[None, :, :]) ** 2).sum(axis=-1)
    return affine, np.exp(-0.5 * d2 / LENGTH ** 2)


@dataclass
class Posterior:
    """The posterior of an image's field (:func:`posterior_field`).

    Attributes
    ----------
    mean : ndarray of shape (G, I)
        Posterior mean coefficients at the prior's nodes.
    spread : ndarray of shape (G,)
        Posterior standard deviation of the PSF at each node, relative to its norm.
    scales : dict
        ``span``, ``tilt``, ``affine``, ``smooth``: the prior's scales of highest
        evidence (relative to the family's own spread), and ``log_evidence``.
    log_scales : ndarray of shape (4,)
        Their log10 (to reuse them: :func:`posterior_field`'s ``log_scales``).
    weights : ndarray of shape (K,)
        Posterior mean of the weights ``w_k`` of the family's conditions.
    amplitudes : ndarray of shape (P,)
    """

    mean: np.ndarray
    spread: np.ndarray
    scales: dict
    log_scales: np.ndarray
    weights: np.ndarray
    amplitudes: np.ndarray


def _span_parts(prior: FieldPrior, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The span's directions at ``points`` (P I, K), and those of the span's weights
    varying over the field as a plane (P I, 2 K): ``sqrt(12) u f_k``."""
    _, span = prior.at(points)  # (K, P, I)
    u = prior.scaled(points)
    tilt = np.sqrt(12.0) * np.concatenate([span * u[None, :, 0, None],
                                           span * u[None, :, 1, None]])
    return (span.reshape(len(span), -1).T, tilt.reshape(len(tilt), -1).T)


def _parts(prior: FieldPrior, centers: np.ndarray):
    """The prior's covariance between the beads, in four parts, (P I, P I) each."""
    u, t = _span_parts(prior, centers)
    ka, ks = spatial_kernels(prior.scaled(centers), prior.scaled(centers))
    return u @ u.T, t @ t.T, np.kron(ka, prior.coef_cov), np.kron(ks, prior.coef_cov)


def _log_evidence(theta, parts, resid, noise) -> float:
    cov = sum(10.0 ** (2 * t) * p for t, p in zip(theta, parts, strict=True)) + np.diag(noise)
    try:
        f = cho_factor(cov, lower=True)
    except np.linalg.LinAlgError:
        return -np.inf
    alpha = cho_solve(f, resid)
    return float(-0.5 * resid @ alpha - np.log(np.diag(f[0])).sum())


def choose_scales(parts, resid: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, float]:
    """log10 of the scales of highest evidence, and that evidence (up to a constant): a
    coarse grid, then a bounded quasi-Newton search from its best."""
    lo, hi = LOG_BOUNDS
    coarse = np.arange(lo, hi + 1e-9, 1.0)
    best, best_val = None, -np.inf
    for t in itertools.product(coarse, repeat=len(parts)):
        val = _log_evidence(t, parts, resid, noise)
        if val > best_val:
            best, best_val = np.array(t), val
    res = minimize(lambda t: -_log_evidence(t, parts, resid, noise), best,
                   method="L-BFGS-B", bounds=[(lo, hi)] * len(parts))
    if np.isfinite(res.fun) and -res.fun >= best_val:
        return np.asarray(res.x), float(-res.fun)
    return best, best_val


def posterior_field(prior: FieldPrior, c: np.ndarray, centers: np.ndarray,
                    sd: np.ndarray, *, amplitude_range: tuple[float, float] = (0.5, 2.0),
                    psfs: np.ndarray | None = None, n_iter: int = 3,
                    log_scales: np.ndarray | None = None, spread: bool = True
                    ) -> Posterior:
    """The posterior mean and spread of an image's field given its beads.

    Parameters
    ----------
    prior : FieldPrior
    c : ndarray of shape (P, I)
        The beads' coefficients on the family's PSF basis.
    centers : ndarray of shape (P, 2)
        Their positions (row, column), pixels.
    sd : ndarray of shape (P,)
        Per-pixel noise of each bead's sum-1 patch (the noise of each coefficient).
    amplitude_range : (float, float)
        Range of each bead's amplitude ``g_p`` relative to the field's.
    psfs : ndarray of shape (I, S, S), optional
        The PSF basis, for the spread relative to the PSF's norm (default orthonormal).
    n_iter : int
        Alternations between the field and the amplitudes.
    log_scales : ndarray of shape (4,), optional
        The prior's scales (log10), e.g. those chosen from more beads; default: those
        of highest evidence given these beads.
    spread : bool
        Compute the spread (``Posterior.spread`` is NaN otherwise: the mean alone costs
        a tenth as much).

    Returns
    -------
    Posterior
    """
    c = np.asarray(c, np.float64)
    centers = np.asarray(centers, np.float64).reshape(-1, 2)
    n_p, n_i = c.shape
    sd = np.asarray(sd, np.float64).reshape(n_p)
    good = np.isfinite(sd) & (sd > 0)
    sd = np.where(good, sd, np.median(sd[good]) if good.any() else 1.0)
    mean_b, _ = prior.at(centers)
    parts = _parts(prior, centers)
    noise = np.repeat(sd ** 2, n_i)
    g = np.ones(n_p)
    a, b = amplitude_range
    theta = None if log_scales is None else np.asarray(log_scales, np.float64)
    evidence = None
    for _ in range(int(n_iter)):
        resid = (c / g[:, None] - mean_b).ravel()
        noise_g = noise / np.repeat(g ** 2, n_i)
        if theta is None:
            theta, evidence = choose_scales(parts, resid, noise_g)
        scale = 10.0 ** (2 * theta)
        prior_cov = sum(s * p for s, p in zip(scale, parts, strict=True))
        f = cho_factor(prior_cov + np.diag(noise_g), lower=True)
        alpha = cho_solve(f, resid)
        fit = mean_b + (prior_cov @ alpha).reshape(n_p, n_i)
        mm = (fit * fit).sum(axis=1)
        g = np.where(mm > 0, (fit * c).sum(axis=1) / np.maximum(mm, 1e-300), 1.0).clip(a, b)
    mean = prior.mean + _cross_times(prior, prior.nodes, centers, scale, alpha)
    sd_psf = (_spread(prior, _cross(prior, prior.nodes, centers, scale), f, scale, mean,
                      psfs) if spread else np.full(len(mean), np.nan))
    span_b, _ = _span_parts(prior, centers)
    names = ("span", "tilt", "affine", "smooth")
    return Posterior(mean, sd_psf,
                     {**{k: float(10 ** t) for k, t in zip(names, theta, strict=True)},
                      "log_evidence": None if evidence is None else float(evidence)},
                     theta, scale[0] * (span_b.T @ alpha), g)


def _cross(prior: FieldPrior, points: np.ndarray, centers: np.ndarray,
           scale: np.ndarray) -> np.ndarray:
    """The prior covariance between the field at ``points`` (nodes, exactly) and at the
    beads, (len(points) I, P I)."""
    u_p, t_p = _span_parts(prior, points)
    u_b, t_b = _span_parts(prior, centers)
    ka, ks = spatial_kernels(prior.scaled(points), prior.scaled(centers))
    return (scale[0] * u_p @ u_b.T + scale[1] * t_p @ t_b.T
            + scale[2] * np.kron(ka, prior.coef_cov) + scale[3] * np.kron(ks, prior.coef_cov))


def _cross_times(prior: FieldPrior, points: np.ndarray, centers: np.ndarray,
                 scale: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``_cross(...) @ alpha`` as (len(points), I), without forming the cross covariance
    (a Kronecker product times a vector is two small products)."""
    n_i = prior.mean.shape[1]
    u_p, t_p = _span_parts(prior, points)
    u_b, t_b = _span_parts(prior, centers)
    ka, ks = spatial_kernels(prior.scaled(points), prior.scaled(centers))
    a = alpha.reshape(len(centers), n_i)
    out = (scale[0] * u_p @ (u_b.T @ alpha) + scale[1] * t_p @ (t_b.T @ alpha)).reshape(
        len(points), n_i)
    return out + (scale[2] * ka + scale[3] * ks) @ a @ prior.coef_cov.T


def _spread(prior: FieldPrior, cross: np.ndarray, factor, scale: np.ndarray,
            mean: np.ndarray, psfs: np.ndarray | None) -> np.ndarray:
    """Posterior sd of the PSF at each node over its norm (G,)."""
    n_g, n_i = mean.shape
    if psfs is None:
        gram = np.eye(n_i)
    else:
        h = np.asarray(psfs, np.float64).reshape(n_i, -1)
        gram = h @ h.T
    # prior variance at each node: span + kernels (k_a(u, u) = 1 + 12 |u|^2, k_s = 1)
    u = prior.scaled(prior.nodes)
    span = prior.span.transpose(1, 0, 2)  # (G, K, I)
    on_span = np.einsum("gki,ij,gkj->g", span, gram, span)
    prior_var = ((scale[0] + scale[1] * 12 * (u * u).sum(axis=1)) * on_span
                 + (scale[2] * (1 + 12 * (u * u).sum(axis=1)) + scale[3])
                 * float(np.trace(gram @ prior.coef_cov)))
    solved = cho_solve(factor, cross.T)  # (P I, G I)
    # reduction of the variance, node by node: trace(gram cross_g S^-1 cross_g^T)
    cg = cross.reshape(n_g, n_i, -1)
    sg = solved.T.reshape(n_g, n_i, -1)
    reduction = np.einsum("gip,ij,gjp->g", cg, gram, sg)
    var = np.clip(prior_var - reduction, 0, None)
    norm = np.sqrt(np.einsum("gi,ij,gj->g", mean, gram, mean))
    return np.sqrt(var) / np.maximum(norm, 1e-300)
