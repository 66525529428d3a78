"""Coordinate descent on the sparse part's support: the tail of the deconvolution.

FISTA (:mod:`.fista`) finds the support of the point sources quickly and then spends
most of its iterations concentrating each source's cluster: neighbouring pixels seen
through the blur are nearly the same column of ``H``, the slow direction of any
gradient method (late iterations shrink the support and sharpen the beads while the
objective hardly moves; ``bench/bench_deblur_tol.py``). Coordinate descent treats one
pixel at a time exactly, so correlated columns cost it nothing; restricted to the
support it is cheap (one column is the PSF at the pixel: ``P^2`` multiply-adds per
update; pixels held at zero are skipped until a full sweep checks them again, so a
sweep costs less than one FISTA iteration's FFTs).

With the background ``u2`` fixed, each update minimises the objective of
:func:`~.deconvolve.deblur` over one pixel ``j`` of the support exactly (saturated pixels
enter through the gradient of their one-sided term, with the full column's curvature as
a majoriser: a descent step): ``u_j <- max(0, u_j + (<h_j, e> - gamma_j) / ||h_j||^2)``,
``e`` the residual, which is updated in place.
"""

from __future__ import annotations

import time
from collections.abc import Generator

import numpy as np

from ..common.progress import Progress
from ..model.operator import ProductConvolution


def polish_support(
    image: np.ndarray,
    operator: ProductConvolution,
    sparse: np.ndarray,
    smooth: np.ndarray,
    weights: np.ndarray,
    *,
    censored: tuple[np.ndarray, np.ndarray] | None = None,
    tol: float = 1e-4,
    max_sweeps: int = 300,
    window: int = 10,
) -> Generator[Progress, None, tuple[np.ndarray, dict]]:
    """Coordinate descent on the pixels where ``sparse > 0``, the background fixed.

    Parameters
    ----------
    image : ndarray of shape (H, W), float32
        The data ``y``.
    operator : ProductConvolution
        ``H``.
    sparse, smooth : ndarray of shape (H, W)
        ``u1`` (its support is where the updates happen) and ``u2`` (fixed).
    weights : ndarray of shape (H, W)
        ``gamma1`` per pixel.
    censored : tuple of index arrays, optional
        Saturated pixels: lower bounds on ``H u``.
    tol : float
        Stop when the objective falls by less than ``tol`` (relatively) over ``window``
        sweeps (the rule FISTA's iterations stop by).
    max_sweeps : int
        Sweeps at most.

    Yields
    ------
    Progress
        Every 10 sweeps (stop the generator there to cancel).

    Returns
    -------
    (sparse, info)
        ``u1`` after the sweeps (float32) and ``{"sweeps", "converged", "objective_fall",
        "support_before", "support_after", "seconds"}``.
    """
    t0 = time.perf_counter()
    h, w = image.shape
    p = operator.psf_size
    flat = np.flatnonzero(sparse > 0)
    ys, xs = np.divmod(flat, w)
    u = sparse.ravel()[flat].astype(np.float64)
    gam = weights.ravel()[flat].astype(np.float64)
    info = {"sweeps": 0, "converged": True, "objective_fall": 0.0,
            "support_before": int(flat.size), "support_after": int(flat.size)}
    if flat.size == 0:
        return sparse.astype(np.float32), info
    cols, norm2, residual, lower = _columns(image, operator, sparse, smooth, censored, ys, xs)
    e0 = _effective(residual, lower)
    data = 0.5 * float(np.vdot(e0, e0))
    value = data + float(np.vdot(gam, u))
    history = [value]
    n, wins, bounds, col_list, u_l, n2_l, gam_l, everyone, alive, active = _per_pixel(
            p, flat, xs, ys, u, gam, cols, norm2, residual, lower)
    for sweep in range(int(max_sweeps)):
        full = len(active) == n
        change = 0.0
        for j in active:
            win, col, gj, n2, uj = wins[j], col_list[j], gam_l[j], n2_l[j], u_l[j]
            box = bounds[j]
            g = float(np.vdot(col, win if box is None else _effective(win, box)))
            new = max(0.0, uj + (g - gj) / n2) if n2 > 0 else 0.0
            d = new - uj
            if d != 0.0:
                win -= np.float32(d) * col
                # exact for the quadratic term; a bound where pixels are censored
                change += -g * d + 0.5 * n2 * d * d + gj * d
                u_l[j] = new
            # at zero and held there (its correlation below its weight): skipped by
            # the next sweeps until a full sweep checks it again
            alive[j] = new > 0.0 or g >= gj
        history.append(history[-1] + change)
        info["sweeps"] = sweep + 1
        if (sweep + 1) % 10 == 0:
            yield Progress("polish", (sweep + 1) / max_sweeps,
                           f"polish sweep {sweep + 1}: {sum(v > 0 for v in u_l)} points")
        if len(history) > window and (history[-1 - window] - history[-1]
                                      <= tol * abs(history[-1])):
            if full:
                break
            active = everyone  # converged on the pixels still moving: check them all
            alive = [True] * n
        else:
            active = [j for j in active if alive[j]]
    u = np.asarray(u_l)
    out = np.zeros(h * w, np.float32)
    out[flat] = u
    info["objective_fall"] = float(history[0] - history[-1])
    info["support_after"] = int((u > 0).sum())
    info["seconds"] = round(time.perf_counter() - t0, 3)
    return out.reshape(h, w), info


def _columns(image, operator, sparse, smooth, censored, ys, xs):
    """The support's columns (the PSF at each pixel, unnormalised as ``H`` applies it, cut
    to the image) and their squared norms, the residual on the image padded by half a PSF,
    and its censored pixels (None where none is)."""
    h, w = image.shape
    p = operator.psf_size
    c = p // 2
    alpha = operator.coefficients_at(ys.astype(float), xs.astype(float))  # (n, I)
    cols = np.tensordot(alpha, operator.basis, axes=(-1, 0)).astype(np.float32)
    inside = np.zeros((h + 2 * c, w + 2 * c), np.float32)
    inside[c:c + h, c:c + w] = 1.0
    for j in range(len(ys)):
        cols[j] *= inside[ys[j]:ys[j] + p, xs[j]:xs[j] + p]
    norm2 = np.einsum("jab,jab->j", cols, cols).astype(np.float64)
    residual = np.zeros_like(inside)
    residual[c:c + h, c:c + w] = image - operator.apply(
        (sparse + smooth).astype(np.float32))
    lower = None
    if censored is not None:
        lower = np.zeros(inside.shape, bool)
        lower[censored[0] + c, censored[1] + c] = True
    return cols, norm2, residual, lower


def _per_pixel(p, flat, xs, ys, u, gam, cols, norm2, residual, lower):
    """Python scalars and per-pixel views (each pixel's window of the residual, its censored
    pixels, column, weight, squared norm and value): the sweeps are where the time goes."""
    n = int(flat.size)
    wins = [residual[y0:y0 + p, x0:x0 + p] for y0, x0 in zip(ys.tolist(), xs.tolist(),
                                                              strict=True)]
    bounds = [None] * n
    if lower is not None:
        for k, (y0, x0) in enumerate(zip(ys.tolist(), xs.tolist(), strict=True)):
            box = lower[y0:y0 + p, x0:x0 + p]
            bounds[k] = box if box.any() else None
    col_list = list(cols)
    gam_l, n2_l, u_l = gam.tolist(), norm2.tolist(), u.tolist()
    everyone = list(range(n))
    active, alive = everyone, [True] * n
    return n, wins, bounds, col_list, u_l, n2_l, gam_l, everyone, alive, active


def _effective(residual: np.ndarray, lower: np.ndarray | None) -> np.ndarray:
    """The residual where the data term is two-sided, its positive part where the pixel
    is only a lower bound (saturated)."""
    if lower is None:
        return residual
    return np.where(lower, np.maximum(residual, 0), residual)
