"""Error metrics between an estimated and a true PSF.

The paper compares operators by a rescaled relative l2 distance: the intensity of a bead
and the gain of a microscope cannot be told apart, so the estimate may be rescaled.
A bead of unknown position fixes its PSF only up to a translation, so the aligned
metric also moves the estimate by the best sub-pixel translation (Fourier shift).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.optimize import minimize


def rescaled_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """``min_c ||c * estimate - truth|| / ||truth||`` (closed form)."""
    t = np.asarray(truth, dtype=np.float64).ravel()
    tn = float(np.dot(t, t))
    if tn <= 0:
        raise ValueError("`truth` is zero: the relative error is undefined.")
    return _rescaled(np.asarray(estimate, dtype=np.float64).ravel(), t, tn)


def _rescaled(e: np.ndarray, t: np.ndarray, tn: float) -> float:
    """:func:`rescaled_error` of the flat float64 ``e`` and ``t``, ``tn = t . t > 0``
    (computed once by a caller that tries many ``e``)."""
    ee = float(np.dot(e, e))
    if ee <= 0:
        return 1.0
    c = float(np.dot(e, t)) / ee
    return float(np.sqrt(max(tn - c * np.dot(e, t), 0.0) / tn))


@lru_cache(maxsize=64)
def _toeplitz(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The lags ``-(n - 1) .. n - 1`` of an (n, n) Toeplitz matrix, and the index of
    each of its entries into them (read-only)."""
    lags = np.arange(-(n - 1), n)
    index = np.arange(n)[:, None] - np.arange(n)[None, :] + n - 1
    lags.flags.writeable = index.flags.writeable = False
    return lags, index


def _shift_matrix(n: int, period: int, s: float) -> np.ndarray:
    """The (n, n) matrix that translates a length-``n`` signal by ``s`` pixels (``out[i] =
    sum_j D(i - j - s) in[j]``): the Fourier shift on a zero-padded grid of odd length
    ``period``, cropped back to the signal, with ``D(u) = sin(pi u) / (period sin(pi u /
    period))`` the periodic band-limited (Dirichlet) kernel (Toeplitz: ``2 n - 1``
    values; the lags and the layout are kept per ``n``: the error of every accuracy test
    and bench evaluates it hundreds of thousands of times)."""
    lags, index = _toeplitz(n)
    u = lags - float(s)
    den = period * np.sin(np.pi * u / period)
    small = np.abs(den) < 1e-12
    d = np.where(small, 1.0, np.sin(np.pi * u) / np.where(small, 1.0, den))
    return d[index]


def _period(p: int) -> int:
    """The odd length ``2 p + 3`` of the zero-padded grid the Fourier shift acts on (the
    shifted signal never wraps onto itself; odd: no Nyquist frequency to choose a
    convention for)."""
    return 2 * p + 3


def _shifter(estimate: np.ndarray):
    """Return ``f(shift) -> estimate translated by shift`` (Fourier, zero-padded x2):
    separable (n, n) matrices, far cheaper than a padded FFT per shift."""
    est = np.asarray(estimate, dtype=np.float64)
    py, px = est.shape[-2:]
    ty, tx = _period(py), _period(px)

    def shifted(s):
        return _shift_matrix(py, ty, s[0]) @ est @ _shift_matrix(px, tx, s[1]).T

    return shifted


def best_shift(estimate: np.ndarray, truth: np.ndarray, max_shift: float = 2.0):
    """Sub-pixel translation of ``estimate`` that minimises the rescaled error.

    Returns
    -------
    shift : ndarray of shape (2,)
        (row, column) translation in pixels, within ``max_shift``.
    error : float
        The rescaled relative error after that translation.
    """
    shifted = _shifter(estimate)
    t = np.asarray(truth, dtype=np.float64).ravel()
    tn = float(np.dot(t, t))
    if tn <= 0:
        raise ValueError("`truth` is zero: the relative error is undefined.")

    def cost(s):
        if np.max(np.abs(s)) > max_shift:
            return 1.0 + float(np.max(np.abs(s)))
        return _rescaled(shifted(s).ravel(), t, tn)

    # start from the centroid difference
    def centroid(a):
        a = np.clip(np.asarray(a, dtype=np.float64), 0, None)
        g = np.arange(a.shape[0])
        tot = max(a.sum(), 1e-300)
        return np.array([(a.sum(axis=1) @ g) / tot, (a.sum(axis=0) @ g) / tot])

    s0 = np.clip(centroid(truth) - centroid(estimate), -max_shift, max_shift)
    best = None
    for start in (s0, np.zeros(2)):
        res = minimize(cost, start, method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-7, "initial_simplex":
                                start + np.array([[0, 0], [0.2, 0], [0, 0.2]])})
        if best is None or res.fun < best.fun:
            best = res
    return np.asarray(best.x), float(best.fun)


def psf_error(estimate: np.ndarray, truth: np.ndarray, *, align: bool = True) -> float:
    """Rescaled relative l2 error between two PSF patches of the same shape.

    Parameters
    ----------
    estimate, truth : ndarray of shape (P, P)
    align : bool
        Also minimise over a sub-pixel translation of ``estimate`` (within 2 pixels).

    Returns
    -------
    float
        ``min_{c, s} ||c * T_s estimate - truth|| / ||truth||``.
    """
    estimate = np.asarray(estimate, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if estimate.shape != truth.shape:
        raise ValueError(
            f"`estimate` and `truth` must have the same shape, got {estimate.shape} and "
            f"{truth.shape}."
        )
    if not align:
        return rescaled_error(estimate, truth)
    return best_shift(estimate, truth)[1]


def psf_error_3d(estimate: np.ndarray, truth: np.ndarray, *, max_shift: float = 2.0
                 ) -> float:
    """Rescaled relative l2 error between two 3D PSFs (Z, P, P) after the best lateral
    sub-pixel translation, one for every plane (a bead's lateral centre is one point):
    ``min_{c, s} ||c T_s estimate - truth|| / ||truth||``."""
    est = np.asarray(estimate, dtype=np.float64)
    tru = np.asarray(truth, dtype=np.float64)
    if est.shape != tru.shape or est.ndim != 3:
        raise ValueError(f"`estimate` and `truth` must be volumes of one shape, got "
                         f"{est.shape} and {tru.shape}")
    shifted = _shifter(est)
    t = tru.ravel()
    tn = float(np.dot(t, t))
    if tn <= 0:
        raise ValueError("`truth` is zero: the relative error is undefined.")

    def cost(s):
        if np.max(np.abs(s)) > max_shift:
            return 1.0 + float(np.max(np.abs(s)))
        return _rescaled(shifted(s).ravel(), t, tn)

    s0 = best_shift(est.sum(axis=0), tru.sum(axis=0), max_shift)[0]
    res = minimize(cost, s0, method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-7,
                            "initial_simplex": s0 + np.array([[0, 0], [0.2, 0], [0, 0.2]])})
    return float(min(res.fun, cost(s0)))


def grid_positions(shape, n: int = 8, *, layout: str = "cells", margin: float = 0.0):
    """Field positions of an ``n x n`` evaluation grid.

    Parameters
    ----------
    shape : tuple of int
        Image shape (rows, columns).
    n : int
        Grid size.
    layout : {"cells", "edges"}
        "cells": the centres of an ``n x n`` tiling of the field (midpoint rule: the mean
        over the grid estimates the mean over the field). "edges": from ``margin`` to
        the opposite border, so the outer ring of the grid lies on the field's edge
        (stresses extrapolation beyond the outermost beads).
    margin : float
        Distance to the border of the "edges" layout, in pixels.

    Returns
    -------
    ys, xs : ndarray of shape (n,)
    """
    h, w = shape
    if layout == "cells":
        return (np.arange(n) + 0.5) * h / n - 0.5, (np.arange(n) + 0.5) * w / n - 0.5
    if layout == "edges":
        return np.linspace(margin, h - 1 - margin, n), np.linspace(margin, w - 1 - margin, n)
    raise ValueError(f"`layout` must be 'cells' or 'edges', got {layout!r}.")


def grid_errors(operator, truth, n: int = 8, *, align: bool = True,
                layout: str = "cells") -> np.ndarray:
    """Errors of ``operator.psf_at`` against ``truth.psf_at`` on an ``n x n`` grid.

    Parameters
    ----------
    operator : ProductConvolution
    truth : object with ``psf_at(y, x, size)`` (e.g. the simulator's ``SimulationTruth``)
    n : int
        Grid size.
    align : bool
        Minimise over a sub-pixel translation too.
    layout : {"cells", "edges"}
        See :func:`grid_positions` ("edges" uses a margin of half a patch).

    Returns
    -------
    ndarray of shape (n, n)
    """
    ys, xs = grid_positions(operator.image_shape, n, layout=layout, margin=operator.psf_size // 2)
    err = np.empty((n, n))
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            err[i, j] = psf_error(operator.psf_at(y, x), truth.psf_at(y, x, operator.psf_size),
                                  align=align)
    return err


def shift_invariant_errors(truth, size: int, shape, n: int = 8, *, align: bool = True,
                           layout: str = "cells"):
    """Errors of the best single shift-invariant PSF (the mean of the true PSFs).

    Returns
    -------
    ndarray of shape (n, n)
    """
    ys, xs = grid_positions(shape, n, layout=layout, margin=size // 2)
    true = np.array([[truth.psf_at(y, x, size) for x in xs] for y in ys])
    mean = true.mean(axis=(0, 1))
    return np.array([[psf_error(mean, true[i, j], align=align) for j in range(n)]
                     for i in range(n)])


def evaluate_against_truth(operator, truth, n: int = 8) -> dict:
    """Error table of an estimated operator against a simulation's ground truth.

    Parameters
    ----------
    operator : ProductConvolution
    truth : SimulationTruth (anything with ``psf_at(y, x, size)``)
    n : int
        The PSFs are compared on an ``n x n`` grid of field positions: the centres of
        an ``n x n`` tiling of the field (see :func:`grid_positions`).

    Returns
    -------
    dict
        ``aligned`` and ``unaligned`` errors of the estimate and ``shift_invariant``
        errors of the best single PSF (the mean of the true PSFs), each with ``mean``
        and ``max``; ``ratio`` = aligned mean / shift-invariant mean; ``edges``: the
        aligned errors on a grid reaching the field's border (half a patch from it);
        and the ``grid`` of aligned errors (n x n list).
    """
    aligned = grid_errors(operator, truth, n)
    unaligned = grid_errors(operator, truth, n, align=False)
    invariant = shift_invariant_errors(truth, operator.psf_size, operator.image_shape, n)
    edges = grid_errors(operator, truth, n, layout="edges")

    def stats(e):
        return {"mean": float(e.mean()), "max": float(e.max())}

    return {
        "aligned": stats(aligned),
        "unaligned": stats(unaligned),
        "shift_invariant": stats(invariant),
        "ratio": float(aligned.mean() / invariant.mean()) if invariant.mean() > 1e-6 else None,
        "edges": stats(edges),
        "grid": aligned.round(5).tolist(),
    }
