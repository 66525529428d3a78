"""Sub-pixel centring of beads (paper, Appendix A, "Shift and re-sampling").

The centre of a bead is the maximum of the correlation of the image with a continuous
Gaussian ``G``: ``c = argmax_z sum_p I(p) G(p - z)``. Setting the gradient to zero gives
the fixed point ``z = sum_p I(p) G(p - z) p / sum_p I(p) G(p - z)``, a Gaussian-weighted
centroid iterated to convergence (mean shift). It is vectorised over beads.
"""

from __future__ import annotations

import numpy as np

from ..common.progress import check_halt


def gather_windows(image: np.ndarray, centers: np.ndarray, half: int) -> np.ndarray:
    """Square windows of ``image`` around integer-rounded centres.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    centers : ndarray of shape (K, 2)
        Centres (row, column) in pixels.
    half : int
        Half-width: windows are ``(2 half + 1, 2 half + 1)``. Indices outside the image
        are clamped to the nearest edge pixel.

    Returns
    -------
    ndarray of shape (K, 2 half + 1, 2 half + 1)
    """
    h, w = image.shape
    iy = np.round(centers[:, 0]).astype(np.intp)
    ix = np.round(centers[:, 1]).astype(np.intp)
    d = np.arange(-half, half + 1)
    rows = np.clip(iy[:, None, None] + d[None, :, None], 0, h - 1)
    cols = np.clip(ix[:, None, None] + d[None, None, :], 0, w - 1)
    return image[rows, cols]


def refine_centers(
    image: np.ndarray,
    centers,
    *,
    sigma: float,
    half: int | None = None,
    max_iter: int = 50,
    tol: float = 1e-4,
) -> np.ndarray:
    """Sub-pixel bead centres: maxima of the correlation with a Gaussian.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    centers : array_like of shape (K, 2)
        Starting centres (row, column) in pixels, e.g. the detected peaks.
    sigma : float
        Standard deviation of the Gaussian in pixels, about the width of the PSF core.
    half : int, optional
        Half-width of the window used around each bead; default ``ceil(3 sigma)``.
    max_iter : int
        Maximum number of fixed-point iterations.
    tol : float
        Stop when no centre moves by more than ``tol`` pixels.

    Returns
    -------
    ndarray of shape (K, 2), float64
        Refined centres. A centre stays within ``half`` pixels of the pixel nearest its
        start; beads whose window has no signal above the local background keep their
        start exactly.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    if len(centers) == 0:
        return centers.copy()
    if half is None:
        half = int(np.ceil(3 * sigma))
    win = gather_windows(image, centers, half).astype(np.float64)
    # local background: median of the window's edge pixels
    edge = np.concatenate(
        [win[:, 0, :], win[:, -1, :], win[:, 1:-1, 0], win[:, 1:-1, -1]], axis=1
    )
    win = np.clip(win - np.median(edge, axis=1)[:, None, None], 0, None)
    grid = np.arange(-half, half + 1, dtype=np.float64)
    base = np.round(centers)  # the windows are centred on these pixels
    offset = centers - base  # start where the caller said, so a bead without signal stays
    inv2s2 = 0.5 / sigma**2
    for _ in range(max_iter):
        check_halt()
        gy = np.exp(-((grid[None, :] - offset[:, :1]) ** 2) * inv2s2)  # (K, n)
        gx = np.exp(-((grid[None, :] - offset[:, 1:]) ** 2) * inv2s2)  # (K, n)
        wgt = win * gy[:, :, None] * gx[:, None, :]
        total = wgt.sum(axis=(1, 2))
        ok = total > 0
        new = offset.copy()
        if ok.any():
            new[ok, 0] = wgt[ok].sum(axis=2) @ grid / total[ok]
            new[ok, 1] = wgt[ok].sum(axis=1) @ grid / total[ok]
        new = np.clip(new, -half, half)
        moved = np.abs(new - offset).max()
        offset = new
        if moved < tol:
            break
    return base + offset
