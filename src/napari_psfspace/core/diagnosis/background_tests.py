"""Residual tests of the pixels between the beads: outlier pixels, a smooth background
over the bead-free mask, row and column patterns (fixed-pattern offsets) and structure
in windows of the background.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy import ndimage as ndi
from scipy import stats

from ..beads.background import monomials
from ..beads.noise import NoiseModel
from ..beads.spikes import find_spikes, pixel_noise_sd
from ..common.progress import check_halt
from .statistics import LINE_CLIP, excess_z, trim_factor


def outlier_pixels(img: np.ndarray, noise: NoiseModel, k: float = 8.0) -> np.ndarray:
    """Pixels narrower than the optics can form (hot pixels, cosmic rays) standing ``k``
    noise sd out (:func:`~napari_psfspace.core.beads.spikes.find_spikes`), shape (S, 2); the
    noise sd is the model's at the image's median level, or the image's own where that
    is larger."""
    sd = float(np.sqrt(noise.variance(float(np.median(img[::4, ::4])))))
    return find_spikes(img, noise_sd=max(sd, pixel_noise_sd(img)), k=k)


def pixel_outliers(img: np.ndarray, noise: NoiseModel, k: float = 8.0) -> dict:
    found = outlier_pixels(img, noise, k)
    return {"count": int(len(found)), "positions": found[:200].tolist()}


def bead_free_mask(shape, positions, psf_radius: float) -> np.ndarray:
    """True farther than ``1.5 psf_radius`` from every position, shape ``shape``."""
    mask = np.zeros(shape, bool)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    iy = np.clip(np.round(pos[:, 0]).astype(int), 0, shape[0] - 1)
    ix = np.clip(np.round(pos[:, 1]).astype(int), 0, shape[1] - 1)
    mask[iy, ix] = True
    return ~ndi.binary_dilation(mask, iterations=int(np.ceil(1.5 * psf_radius)))


def smooth_background(img: np.ndarray, free: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised (masked) Gaussian smoothing of the bead-free pixels."""
    check_halt()
    num = ndi.gaussian_filter(np.where(free, img, 0.0), sigma, mode="nearest")
    den = ndi.gaussian_filter(free.astype(np.float64), sigma, mode="nearest")
    return num / np.maximum(den, 1e-6)


#: a line's neighbours: the mean of the +-4 lines around it (itself left out)
NEIGHBOURS = np.r_[np.ones(4), 0.0, np.ones(4)] / 8.0


def line_levels(resid: np.ndarray, level: np.ndarray, free: np.ndarray, noise: NoiseModel,
                axis: int) -> dict:
    """Level of each row (axis=1) or column (axis=0) of the bead-free, detrended pixels
    ``resid``: ``mean``, shape (n_lines,), the mean of its pixels within LINE_CLIP noise
    sd of its median; ``count``, ``level`` (the smooth background's median along the
    line, ADU), ``half`` (the clip's half width, ADU) and ``ok`` (lines with 20 pixels
    inside or more)."""
    data = np.where(free, resid, np.nan)
    lvl = np.where(free, level, np.nan)
    if axis == 0:  # one line per row of the transposed arrays
        data, lvl = data.T, lvl.T
    with warnings.catch_warnings():  # lines without a bead-free pixel: NaN, left out
        warnings.simplefilter("ignore", RuntimeWarning)
        lev = np.nanmedian(lvl, axis=1)
        centre = np.nanmedian(data, axis=1)
    # the mean within the clip is robust to a faint bead's wing or a hot pixel, and,
    # unlike the median (or a trimmed mean), not stuck to whole ADU on an integer image
    # whose noise is below one ADU (an 8-bit low-gain scene's medians flip between two
    # integers from line to line: z 20-75 on still scenes of the family). On integer
    # images the window spans at least +-1.5 ADU, so that the neighbours of the median's
    # integer stay in
    sd = np.sqrt(noise.variance(np.nan_to_num(lev)))
    half = np.maximum(LINE_CLIP * sd, 1.5 if noise.min_variance > 0 else 0.0)
    with np.errstate(invalid="ignore"):
        inside = np.abs(data - centre[:, None]) <= half[:, None]
    count = inside.sum(axis=1)
    mean = np.where(inside, data, 0.0).sum(axis=1) / np.maximum(count, 1)
    return {"mean": mean, "count": count, "level": lev, "half": half, "sd": sd,
            "ok": (count >= 20) & np.isfinite(centre)}


def line_pattern(resid: np.ndarray, level: np.ndarray, free: np.ndarray, noise: NoiseModel,
                  axis: int, scale_error: float = 0.0) -> dict:
    """Excess variance of the clipped means of bead-free, detrended pixels along rows
    (axis=1) or columns (axis=0), line to line, as a z against the noise (with the
    noise model's relative error ``scale_error``, see :func:`noise_scale_error`)."""
    check_halt()
    d = line_levels(resid, level, free, noise, axis)
    ok = d["ok"]
    if ok.sum() < 10:
        return {"z": 0.0, "n_lines": int(ok.sum())}
    m = d["mean"][ok]
    # a fixed pattern is line-to-line jitter: compare each line with the mean of its
    # +-4 neighbours (slow trends of the background left by the smoothing cancel out)
    dev = m - ndi.convolve1d(m, NEIGHBOURS, mode="reflect")
    # variance of the mean of normal values clipped at +-c sd
    c = d["half"][ok] / d["sd"][ok]
    clipped = 1.0 - 2.0 * c * stats.norm.pdf(c) / np.maximum(2.0 * stats.norm.cdf(c) - 1.0,
                                                             1e-12)
    var_line = clipped * noise.variance(d["level"][ok]) / d["count"][ok]
    n = int(ok.sum())
    ratio = float(np.mean(dev**2 / (var_line * (1 + 1 / 8))))
    return {"z": excess_z(ratio, np.sqrt(2.0 / n), scale_error), "n_lines": n,
            "chi2_dof": ratio, "rms_adu": float(np.sqrt(np.mean(dev**2)))}


def window_structure(resid: np.ndarray, level: np.ndarray, free: np.ndarray,
                      noise: NoiseModel, size: int, *, min_free: float = 0.25,
                      trim: float = 0.1, scale_error: float = 0.0) -> dict:
    """Order-2 polynomials fitted to the bead-free pixels of windows of a patch's size.

    The image is tiled with ``size x size`` windows; those whose bead-free fraction is
    at least ``min_free`` (with a large PSF, or structure detected as beads, hardly any
    window is wholly bead-free) get an order-2 polynomial fitted by least squares to
    their bead-free pixels, and the chi-square of the fit under the noise model becomes
    a normal z (Wilson-Hilferty). Structure sits
    in some windows only: the statistic is the ``trim``-trimmed mean of the windows' z
    (robust to a few windows spoilt by a bead's wing or a hot pixel), scaled to unit
    variance under the null (1.0605 / n for a 10 % trim of normal values).

    Parameters
    ----------
    resid : ndarray of shape (M, N)
        Image minus its smooth background, ADU.
    level : ndarray of shape (M, N)
        Smooth background, ADU (the noise model's expected value).
    free : ndarray of shape (M, N), bool
        Bead-free pixels.
    noise : NoiseModel
    size : int
        Window size, pixels (the patch size).

    Returns
    -------
    dict
        ``z``, ``windows`` (number used), ``median_chi2_dof``.
    """
    check_halt()
    design = monomials(size, 2)
    n_par = design.shape[1]
    h, w = resid.shape
    ratios, dofs = [], []
    for y0 in range(0, h - size + 1, size):
        for x0 in range(0, w - size + 1, size):
            use = free[y0:y0 + size, x0:x0 + size].ravel()
            n_use = int(use.sum())
            if n_use < max(min_free * size * size, 4 * n_par):
                continue
            d = resid[y0:y0 + size, x0:x0 + size].ravel()[use]
            a = design[use]
            coef, *_ = np.linalg.lstsq(a, d, rcond=None)
            var = noise.variance(level[y0:y0 + size, x0:x0 + size].ravel()[use])
            chi2 = float(np.sum((d - a @ coef) ** 2 / var))
            ratios.append(chi2 / (n_use - n_par))
            dofs.append(n_use - n_par)
    if len(ratios) < 5:
        return {"z": 0.0, "windows": len(ratios)}
    n = len(ratios)
    cut = int(trim * n)
    kept = np.sort(ratios)[cut:n - cut]
    # the trimmed mean of the windows' chi2/dof against 1: its sampling error (each
    # window's sqrt(2 / dof), trimmed) combined with the noise model's own relative error
    se = float(np.sqrt(trim_factor(trim) * 2.0 / np.mean(dofs) / n))
    mean = float(np.mean(kept))
    return {"z": excess_z(mean, se, scale_error), "windows": n,
            "chi2_dof": mean, "median_chi2_dof": float(np.median(ratios))}
