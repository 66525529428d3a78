"""Statistics the residual tests share: rank correlations and chi-square as z-scores,
the noise model's scale error, trimmed excess ratios, and the radial trend of a value
over the field (an F-test of a centred paraboloid).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from ..beads.noise import NoiseModel
from .photometry import radial_design, radial_to_monomials


def spearman_z(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Spearman rho and its Fisher z (approximately N(0, 1) under independence)."""
    ok = np.isfinite(x) & np.isfinite(y)
    n = int(ok.sum())
    if n < 8 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return 0.0, 0.0
    rho = float(stats.spearmanr(x[ok], y[ok]).statistic)
    rho = float(np.clip(rho, -0.999999, 0.999999))
    return rho, float(np.arctanh(rho) * np.sqrt((n - 3) / 1.06))


def chi2_to_z(chi2: float, dof: float) -> float:
    """Wilson-Hilferty normal approximation of a chi-square statistic."""
    if dof <= 0:
        return 0.0
    a = 2.0 / (9.0 * dof)
    return float(((chi2 / dof) ** (1.0 / 3.0) - (1 - a)) / np.sqrt(a))


#: Relative uncertainty of the variance scale of an *assumed* noise model (a fallback:
#: constant variance, unit-gain Poisson), for the tests that compare a chi-square with
#: its noise-only value. The unit-gain fallback overestimated an 8-bit low-gain scene's
#: variance 3-20 times on the scene set.
FALLBACK_SCALE_ERROR = 0.5


def noise_scale_error(noise: NoiseModel) -> float:
    """Relative uncertainty of ``noise``'s variance scale: photon transfer's own
    ``gain_relative_error``, 0 for camera values given, :data:`FALLBACK_SCALE_ERROR`
    for an assumed model.

    The background tests compare a chi-square over hundreds of windows or lines with
    its noise-only value: against the sampling error alone, a gain known to a few per
    cent fires them on still scenes. (Measuring the scale on the image's own bead-free
    pixels instead, from second differences, was tried: quantised 8-bit backgrounds and
    faint undetected beads made it worse, ``bench/bench_diagnose.py``.)
    """
    if noise.kind == "camera":
        return 0.0
    if noise.kind == "photon transfer":
        return float((noise.checks or {}).get("gain_relative_error", 0.0) or 0.0)
    return FALLBACK_SCALE_ERROR


#: A line's level is the mean of its bead-free pixels within this many noise sd of its
#: median.
LINE_CLIP = 3.0


def trim_factor(trim: float) -> float:
    """Asymptotic variance of the ``trim``-trimmed mean of n N(0, 1) values, times n:
    ``(1 - 2a - 2c phi(c) + 2a c^2) / (1 - 2a)^2``, ``c`` the ``(1 - a)`` quantile."""
    if trim <= 0:
        return 1.0
    c = float(stats.norm.isf(trim))
    return (1 - 2 * trim - 2 * c * stats.norm.pdf(c) + 2 * trim * c * c) / (1 - 2 * trim) ** 2


def excess_z(ratio: float, se_sampling: float, scale_error: float) -> float:
    """A mean chi2/dof ``ratio`` against 1, in units of its sampling error combined with
    the noise model's own relative error (:func:`noise_scale_error`)."""
    return float((ratio - 1.0) / max(np.hypot(se_sampling, scale_error), 1e-12))


def radial_trend(positions, values, shape, threshold: float) -> dict:
    """F-test of a paraboloid of revolution (free centre) in ``log(values)`` over the
    field: ``z`` (normal equivalent of the F-test's p), ``F``, ``p``, the radial
    coefficients as monomials, and the smallest centred fall-off to the corners
    (``u^2 + v^2 = 2``) these beads would show at ``threshold``."""
    x = radial_design(positions, shape)
    y = np.log(np.asarray(values, dtype=np.float64))
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
    rss1 = float(np.sum((y - x @ beta) ** 2))
    rss0 = float(np.sum((y - y.mean()) ** 2))
    n, q = len(y), x.shape[1] - 1
    f = ((rss0 - rss1) / q) / max(rss1 / (n - q - 1), 1e-300)
    pval = float(stats.f.sf(f, q, n - q - 1))
    # the beads' own brightness spread and their number set the smallest visible
    # fall-off (bench/bench_power.py)
    cov = np.linalg.pinv(x.T @ x) * rss1 / max(n - q - 1, 1)
    g_min = threshold * float(np.sqrt(max(cov[3, 3], 0.0)))
    return {"z": float(stats.norm.isf(max(pval, 1e-300))), "F": float(f), "p": pval,
            "min_corner_loss": float(1.0 - np.exp(-2.0 * g_min)),
            "coefficients": radial_to_monomials(beta).round(4).tolist()}
