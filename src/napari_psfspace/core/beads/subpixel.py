"""Sub-pixel re-sampling of bead patches by a Fourier phase ramp.

A patch is cut around the nearest whole pixel with a margin, its border tapered to its
own edge level by a cosine (Tukey) ramp over the margin so that the periodic wrap of the
discrete Fourier transform meets no step, moved by the bead's sub-pixel offset with a
phase ramp, and cropped to the patch. For a PSF sampled at or above Nyquist this is the
band-limited (sinc) interpolation: exact where the spline interpolation of
:func:`~napari_psfspace.core.beads.patches.resample_patches` smooths.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from .centering import gather_windows

#: Pixels of margin about a patch (at least), tapered before the move.
MIN_MARGIN = 6


def _taper(n: int, margin: int) -> np.ndarray:
    """A 1-D weight: 1 inside, a raised cosine from 1 to 0 over ``margin`` pixels at each
    end."""
    w = np.ones(n)
    ramp = 0.5 - 0.5 * np.cos(np.pi * (np.arange(margin) + 0.5) / margin)
    w[:margin] = ramp
    w[n - margin:] = ramp[::-1]
    return w


def fourier_resample_patches(image: np.ndarray, centers: np.ndarray, size: int,
                             margin: int | None = None) -> np.ndarray:
    """``(size, size)`` patches whose centre pixel lies on each sub-pixel centre, moved by
    a Fourier phase ramp.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    centers : ndarray of shape (K, 2)
        Centres (row, column), pixels.
    size : int
        Odd patch size.
    margin : int, optional
        Pixels cut beyond the patch on each side and tapered (default
        ``max(MIN_MARGIN, size // 4)``).

    Returns
    -------
    ndarray of shape (K, size, size), float64
        The same convention as
        :func:`~napari_psfspace.core.beads.patches.resample_patches`: pixel ``(i, j)``
        samples the image at ``center - size // 2 + (i, j)``. Beyond the image's edge the
        edge pixels repeat.
    """
    centers = np.asarray(centers, np.float64).reshape(-1, 2)
    half = int(size) // 2
    m = max(MIN_MARGIN, int(size) // 4) if margin is None else int(margin)
    wins = gather_windows(image, centers, half + m).astype(np.float64)
    n = wins.shape[-1]
    taper = np.outer(_taper(n, m), _taper(n, m))
    frac = centers - np.round(centers)
    out = np.empty((len(centers), size, size))
    for k in range(len(centers)):
        w = wins[k]
        edge = np.median(np.concatenate([w[0], w[-1], w[:, 0], w[:, -1]]))
        spec = np.fft.fft2(edge + (w - edge) * taper)
        moved = np.fft.ifft2(ndi.fourier_shift(spec, -frac[k])).real
        out[k] = moved[m:m + size, m:m + size]
    return out


__all__ = ["MIN_MARGIN", "fourier_resample_patches"]
