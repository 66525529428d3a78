"""The Laplacian of Gaussian that finds beads: its response in noise units and its local
maxima. Below :mod:`.scale` (which measures the spots' size with it) and :mod:`.detect`
(which finds the beads with it)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy import ndimage as ndi

from ..common.progress import check_halt
from ..common.threads import filter_by_rows
from ..common.validate import as_image


@lru_cache(maxsize=512)  # a pure function of the scale, asked for at every scale and window
def log_kernel_norm(sigma: float) -> float:
    """l2 norm of the scale-normalised LoG kernel ``sigma^2 LoG`` as sampled by
    :func:`scipy.ndimage.gaussian_laplace` (about ``1 / (sigma sqrt(2 pi))``): the
    response's standard deviation for white noise of unit variance."""
    half = int(np.ceil(4 * sigma)) + 1
    delta = np.zeros((2 * half + 1, 2 * half + 1))
    delta[half, half] = 1.0
    return float(sigma**2 * np.linalg.norm(ndi.gaussian_laplace(delta, sigma)))


def log_response(image, sigma: float, *, pixel_sd_floor: float = 0.0) -> np.ndarray:
    """Scale-normalised negative Laplacian of Gaussian, in robust noise units.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    sigma : float
        Gaussian scale in pixels.
    pixel_sd_floor : float
        Smallest per-pixel noise sd (image units) the response's noise level may
        correspond to: for integer images the rounding noise ``sqrt(1/12)``, so that
        a nearly constant integer background (MAD of zero) does not turn every
        one-count bump into a detection.

    Returns
    -------
    ndarray of shape (M, N), float32
        ``-sigma**2 * LoG(image)`` divided by its robust standard deviation (MAD,
        at least ``pixel_sd_floor`` times the kernel's l2 norm) and shifted so that its
        median is 0: a bead of detection strength 10 stands ten noise standard
        deviations above the filtered background.
    """
    check_halt()
    img = as_image(image, dtype=np.float32)
    # the kernel reaches int(4 sigma + 0.5) pixels (scipy's truncate=4): blocks of rows
    # filtered in parallel with that halo give the same result
    resp = filter_by_rows(lambda a: ndi.gaussian_laplace(a, sigma, mode="reflect"), img,
                          int(4 * sigma + 0.5) + 1)
    resp *= -(sigma**2)
    # Robust noise level from a subsample: median and MAD are O(N) but slow on 5 Mpx.
    step = max(1, int(np.sqrt(resp.size / 250_000)))
    sample = resp[::step, ::step]
    med = float(np.median(sample))
    mad = float(np.median(np.abs(sample - med))) * 1.4826
    floor = pixel_sd_floor * log_kernel_norm(sigma) if pixel_sd_floor > 0 else 0.0
    if not np.isfinite(mad) or mad <= floor:
        mad = max(floor, mad if np.isfinite(mad) else 0.0)
    if mad <= 0:
        spread = float(sample.std())
        mad = spread if spread > 0 else 1.0
    resp -= med
    resp /= mad
    return resp


def local_peaks(response: np.ndarray, min_distance: int, threshold: float) -> np.ndarray:
    """Maxima of ``response`` over a ``(2 d + 1)`` square, above ``threshold``, strongest
    first: :func:`skimage.feature.peak_local_max` with ``exclude_border=False``, computed
    on the pixels above the threshold only (the full-image maximum filter cost as much as
    the hot-pixel search it makes room for).

    Returns
    -------
    ndarray of shape (K, 2), int
        ``(row, column)``, by decreasing response; peaks closer than ``d`` (Chebyshev) to
        a stronger one are dropped (plateaus).
    """
    check_halt()
    resp = np.asarray(response)
    h, w = resp.shape
    ys, xs = np.nonzero(resp > threshold)
    if len(ys) == 0:
        return np.zeros((0, 2), np.intp)
    vals = resp[ys, xs]
    for half in (1, int(min_distance)):  # 3 x 3 first: a cheap, exact pre-selection
        if half < 1:
            continue
        d = np.arange(-half, half + 1)
        # clipped indices: the maximum filter's "nearest" mode, whose padding repeats
        # values already in the window
        rows = np.clip(ys[:, None, None] + d[None, :, None], 0, h - 1)
        cols = np.clip(xs[:, None, None] + d[None, None, :], 0, w - 1)
        top = resp[rows, cols].reshape(len(ys), -1).max(axis=1)
        keep = vals >= top
        ys, xs, vals = ys[keep], xs[keep], vals[keep]
    order = np.argsort(-vals, kind="stable")
    peaks = np.column_stack([ys, xs])[order]
    if len(peaks) > 1 and min_distance > 1:  # equal maxima within d: keep the first
        from scipy.spatial import cKDTree

        tree = cKDTree(peaks)
        drop = np.zeros(len(peaks), bool)
        for i, near in enumerate(tree.query_ball_point(peaks, r=min_distance, p=np.inf)):
            if drop[i]:
                continue
            for j in near:
                if j > i and np.abs(peaks[j] - peaks[i]).max() < min_distance:
                    drop[j] = True
        peaks = peaks[~drop]
    return peaks


__all__ = ["local_peaks", "log_kernel_norm", "log_response"]
