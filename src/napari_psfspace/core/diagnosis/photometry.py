"""Throughput of the optics over the field, from the beads' brightness.

A product-convolution operator with PSFs of sum 1 passes the same total intensity
everywhere. Real microscopes do not: the excitation (and the collection) falls off
towards the field's edges, so identical beads look dimmer there. The *throughput*
``t(x)`` is modelled as the exponential of a polynomial of the normalised field
position (degree 0: constant, the plain model; degree 2: a smooth vignetting / tilted
illumination, by default a paraboloid of revolution with a free centre), fitted to the
logarithm of the beads' fitted amplitudes.

Its held-out error is measured like the PSF's: every bead's amplitude is predicted by a
throughput fitted *without* the bead's fold (:func:`crossfit_log_residuals`), and the
error is the mean squared log ratio of measured to predicted amplitude. Beads differ in
brightness by themselves (size, dye load), which sets the floor of this error.
"""

from __future__ import annotations

import numpy as np
from scipy import stats


def _design(positions: np.ndarray, shape: tuple[int, int], degree: int) -> np.ndarray:
    """Monomials ``u^i v^j`` (``i + j <= degree``) of the positions normalised to [-1, 1],
    shape (K, n_terms)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    h, w = shape
    v = (pos[:, 0] - (h - 1) / 2) / (h / 2)
    u = (pos[:, 1] - (w - 1) / 2) / (w / 2)
    cols = [u**i * v**j for d in range(degree + 1) for j in range(d + 1) for i in [d - j]]
    return np.column_stack(cols) if cols else np.ones((len(pos), 1))


def radial_design(positions: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``1, u, v, u^2 + v^2``: a paraboloid of revolution with a free centre, shape
    (K, 4)."""
    x = _design(positions, shape, 2)
    return np.column_stack([x[:, 0], x[:, 1], x[:, 2], x[:, 3] + x[:, 5]])


def radial_to_monomials(coef: np.ndarray) -> np.ndarray:
    """Radial coefficients ``(c, a, b, g)`` as degree-2 monomials ``(c, a, b, g, 0, g)``."""
    c, a, b, g = coef
    return np.array([c, a, b, g, 0.0, g])


def _fit_design(positions, shape, degree: int, radial: bool) -> tuple[np.ndarray, bool]:
    if degree == 2 and radial:
        return radial_design(positions, shape), True
    return _design(positions, shape, degree), False


def fit_throughput(positions, amplitude, shape: tuple[int, int], *, degree: int = 2,
                   radial: bool = True) -> np.ndarray:
    """Least-squares fit of ``log(amplitude)`` by a polynomial of the field position.

    Parameters
    ----------
    positions : array_like of shape (K, 2)
        Bead centres (row, column), pixels.
    amplitude : array_like of shape (K,)
        Fitted bead amplitudes (any unit, > 0).
    shape : tuple of int
        Image shape (H, W).
    degree : int
        Polynomial degree (0: constant).
    radial : bool
        For degree 2: a paraboloid of revolution with a free centre (``1, u, v,
        u^2 + v^2``: vignetting, an off-centre illumination spot), 4 coefficients
        fitted instead of 6: a fall-off to the corners stands out where the full
        quadratic's does not (``bench/bench_power.py``).

    Returns
    -------
    ndarray of shape (n_terms,)
        Coefficients of the monomials ``u^i v^j`` in the order of increasing total
        degree (``1; u, v; u^2, uv, v^2``), ``u`` and ``v`` the column and row
        normalised to [-1, 1] (radial: ``uv`` is 0 and ``u^2``, ``v^2`` are equal).
    """
    amp = np.asarray(amplitude, dtype=np.float64).ravel()
    if np.any(~(amp > 0)):
        raise ValueError("`amplitude` must be positive and finite to fit a throughput.")
    x, rad = _fit_design(positions, shape, degree, radial)
    if len(amp) < x.shape[1] + 2:
        raise ValueError(f"Too few beads to fit a throughput of degree {degree}: "
                         f"{len(amp)}, need at least {x.shape[1] + 2}.")
    coef, *_ = np.linalg.lstsq(x, np.log(amp), rcond=None)
    return radial_to_monomials(coef) if rad else coef


def throughput_at(coefficients, positions, shape: tuple[int, int]) -> np.ndarray:
    """``exp(polynomial)`` at ``positions`` (K, 2), shape (K,)."""
    coef = np.asarray(coefficients, dtype=np.float64)
    degree = int(round((np.sqrt(8 * len(coef) + 1) - 3) / 2))
    return np.exp(_design(positions, shape, degree) @ coef)


def throughput_map(coefficients, grid_y, grid_x, shape: tuple[int, int], *,
                   normalise: bool = True) -> np.ndarray:
    """Throughput on the grid ``grid_y x grid_x`` (pixels), shape (len(y), len(x)).

    With ``normalise`` the map is divided by its mean over the whole field (so an
    operator scaled by it keeps the image's mean intensity).
    """
    yy, xx = np.meshgrid(np.asarray(grid_y, float), np.asarray(grid_x, float), indexing="ij")
    t = throughput_at(coefficients, np.column_stack([yy.ravel(), xx.ravel()]), shape)
    t = t.reshape(yy.shape)
    if normalise:
        # midpoint rule over 64 x 64 cells of the field
        fy = (np.arange(64) + 0.5) * shape[0] / 64 - 0.5
        fx = (np.arange(64) + 0.5) * shape[1] / 64 - 0.5
        gy, gx = np.meshgrid(fy, fx, indexing="ij")
        t = t / throughput_at(coefficients, np.column_stack([gy.ravel(), gx.ravel()]),
                              shape).mean()
    return t


def crossfit_log_residuals(positions, amplitude, fold, shape: tuple[int, int], *,
                           degree: int = 0, use=None, radial: bool = True) -> np.ndarray:
    """Held-out log ratio of measured to predicted amplitude of every bead.

    Parameters
    ----------
    positions : array_like of shape (K, 2)
    amplitude : array_like of shape (K,)
    fold : array_like of shape (K,), int
        Fold of each bead; each fold is predicted by a throughput fitted on the others.
    shape : tuple of int
    degree : int
        Throughput polynomial degree (0: a constant, the plain model).
    use : array_like of shape (K,), bool, optional
        Beads that may train (default: positive amplitudes).
    radial : bool
        Degree 2 as a paraboloid of revolution (see :func:`fit_throughput`).

    Returns
    -------
    ndarray of shape (K,)
        ``log(A_k / t_hat(x_k))``; NaN for beads with a non-positive amplitude or whose
        fold could not be predicted.
    """
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    amp = np.asarray(amplitude, dtype=np.float64).ravel()
    fold = np.asarray(fold).ravel()
    ok = amp > 0
    if use is not None:
        ok &= np.asarray(use, bool)
    out = np.full(len(amp), np.nan)
    logs = np.log(np.where(amp > 0, amp, 1.0))
    x, _ = _fit_design(pos, shape, degree, radial)
    for f in np.unique(fold):
        train = ok & (fold != f)
        test = (fold == f) & (amp > 0)
        if train.sum() < x.shape[1] + 2 or not test.any():
            continue
        coef, *_ = np.linalg.lstsq(x[train], logs[train], rcond=None)
        out[test] = logs[test] - x[test] @ coef
    return out


def trend_p_value(positions, amplitude, shape: tuple[int, int], *, degree0: int = 0,
                  degree1: int = 2, use=None, radial: bool = True, n_perm: int = 4000,
                  seed: int = 0) -> dict:
    """Permutation test that a throughput of ``degree1`` explains the beads' log
    amplitudes better than one of ``degree0`` (nested designs).

    The statistic is the residual sum of squares the extra terms remove (the F-test's
    numerator); its null distribution is drawn by permuting the residuals of the
    smaller model over the beads (Freedman and Lane), so the test holds for any
    brightness distribution (lognormal dye loads, a few doublets), not just Gaussian
    log amplitudes.

    Why not the held-out errors' own paired test: for nested linear models, the paired
    difference of held-out squared errors ``(y - p0)^2 - (y - p1)^2`` carries the
    beads' own scatter twice, and its z is about half the added terms'
    (``bench/bench_power.py``). The held-out drop still measures the size of the gain.

    Parameters
    ----------
    positions : array_like of shape (K, 2)
    amplitude : array_like of shape (K,)
    shape : tuple of int
    degree0, degree1 : int
        Throughput degrees of the smaller and the larger model (``degree0 < degree1``).
    use : array_like of shape (K,), bool, optional
        Beads to test (default: positive amplitudes).
    radial : bool
        Degree 2 as a paraboloid of revolution (see :func:`fit_throughput`).
    n_perm : int
        Permutations (the smallest p reported is ``1 / (n_perm + 1)``).
    seed : int

    Returns
    -------
    dict
        ``p`` (permutation), ``p_f`` (the F-test's, Gaussian theory), ``F``,
        ``n_beads``.
    """
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    amp = np.asarray(amplitude, dtype=np.float64).ravel()
    ok = np.isfinite(amp) & (amp > 0)
    if use is not None:
        ok &= np.asarray(use, bool)
    if degree1 <= degree0:
        raise ValueError(f"`degree1` must exceed `degree0`, got {degree1} <= {degree0}.")
    x0, _ = _fit_design(pos[ok], shape, degree0, radial)
    x1, _ = _fit_design(pos[ok], shape, degree1, radial)
    y = np.log(amp[ok])
    n, q = len(y), x1.shape[1] - x0.shape[1]
    if n < x1.shape[1] + 3:
        return {"p": 1.0, "p_f": 1.0, "F": 0.0, "n_beads": int(n)}
    q0, _ = np.linalg.qr(x0)
    q1, _ = np.linalg.qr(x1)
    r0 = y - q0 @ (q0.T @ y)  # residuals of the smaller model

    def gain(e):  # RSS removed by the extra terms, for residual columns e (n, m)
        return np.sum((q1.T @ e) ** 2, axis=0) - np.sum((q0.T @ e) ** 2, axis=0)

    observed = float(gain(r0[:, None])[0])
    rss1 = float(np.sum(r0**2) - observed)
    f = (observed / q) / max(rss1 / (n - x1.shape[1]), 1e-300)
    rng = np.random.default_rng(seed)
    perm = np.argsort(rng.random((n, n_perm)), axis=0)
    null = gain(r0[perm])
    p = float((1 + np.count_nonzero(null >= observed)) / (n_perm + 1))
    return {"p": p, "p_f": float(stats.f.sf(f, q, n - x1.shape[1])), "F": float(f),
            "n_beads": int(n)}
