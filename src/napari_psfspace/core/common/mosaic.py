"""Arrange PSF patches and maps into single images for figures and napari layers
(normalised, then laid out by :func:`skimage.util.montage`)."""

from __future__ import annotations

import numpy as np
from skimage.util import montage


def mosaic(tiles: np.ndarray, *, gap: int = 1, normalize: str = "each", fill: float = 0.0,
           gamma: float = 1.0) -> np.ndarray:
    """Tile a grid of 2-D patches into one image.

    Parameters
    ----------
    tiles : ndarray of shape (R, C, P, Q) or (K, P, Q)
        Patches on a grid; a flat stack is laid out on a near-square grid.
    gap : int
        Pixels between tiles.
    normalize : {"each", "global", "none"}
        "each" scales every tile to a maximum of 1 (shape comparison), "global" scales
        all by the same maximum, "none" keeps values.
    fill : float
        Value of the gaps (and of empty cells).
    gamma : float
        Display exponent applied after normalisation to non-negative values (< 1 lifts
        faint rings).

    Returns
    -------
    ndarray of shape (R * (P + gap) - gap, C * (Q + gap) - gap), float64
    """
    t = np.asarray(tiles, dtype=np.float64)
    if t.ndim == 3:
        k = t.shape[0]
        cols = int(np.ceil(np.sqrt(k)))
        rows = int(np.ceil(k / cols))
        grid = np.full((rows * cols,) + t.shape[1:], np.nan)
        grid[:k] = t
        t = grid.reshape(rows, cols, *t.shape[1:])
    if t.ndim != 4:
        raise ValueError(f"`tiles` must have shape (R, C, P, Q) or (K, P, Q), got {t.shape}.")
    if normalize not in ("each", "global", "none"):
        raise ValueError(f"`normalize` must be 'each', 'global' or 'none', got {normalize!r}.")
    r, c, p, q = t.shape
    if normalize == "each":
        # (empty cells of a flat stack are NaN: their peak is 0, without a warning)
        peak = np.max(np.where(np.isnan(t), 0.0, np.abs(t)), axis=(2, 3), keepdims=True)
        t = t / np.where(peak > 0, peak, 1.0)
    elif normalize == "global":
        peak = np.nanmax(np.abs(t))
        t = t / (peak if peak > 0 else 1.0)
    if gamma != 1.0:
        t = np.sign(t) * np.abs(t) ** gamma
    # scikit-image's montage pads the outer border too: cropped to gaps between tiles
    flat = np.where(np.isnan(t), fill, t).reshape(r * c, p, q)
    out = montage(flat, fill=fill, grid_shape=(r, c), padding_width=gap)
    return out[gap:out.shape[0] - gap, gap:out.shape[1] - gap] if gap else out
