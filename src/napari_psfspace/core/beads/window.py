"""Radial bump window that confines a PSF patch to its support (paper, Appendix A)."""

from __future__ import annotations

import numpy as np


def bump(t, r: float, r_ext: float) -> np.ndarray:
    """Radial multiplier ``m(t)``: 1 below ``r``, 0 above ``r_ext``, smooth between.

    ``m(t) = exp(1 - 1 / (1 - ((t - r) / (r_ext - r))**2))`` for ``r <= t <= r_ext``.

    Parameters
    ----------
    t : array_like
        Distances to the patch centre, in pixels.
    r, r_ext : float
        Inner and outer radii in pixels, ``0 < r < r_ext``.

    Returns
    -------
    ndarray, same shape as ``t``, values in [0, 1].
    """
    if not 0 < r < r_ext:
        raise ValueError(f"`r` and `r_ext` must satisfy 0 < r < r_ext, got r={r}, r_ext={r_ext}.")
    t = np.asarray(t, dtype=np.float64)
    s = (t - r) / (r_ext - r)
    out = np.zeros_like(t)
    out[t <= r] = 1.0
    mid = (t > r) & (t < r_ext)
    out[mid] = np.exp(1.0 - 1.0 / (1.0 - s[mid] ** 2))
    return out


def radial_distance(size: int) -> np.ndarray:
    """Distance of each pixel of a ``(size, size)`` patch to its centre pixel ``size // 2``."""
    c = size // 2
    d = np.arange(size) - c
    return np.hypot(d[:, None], d[None, :])


def bump_window(size: int, r: float, r_ext: float) -> np.ndarray:
    """The bump multiplier on a ``(size, size)`` patch centred at ``size // 2``."""
    return bump(radial_distance(size), r, r_ext)
