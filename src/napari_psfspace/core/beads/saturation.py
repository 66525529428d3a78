"""Saturation at the beads: which detections have a clipped core, and what a reader must
be told of the image's clipping (the level, the pixels at it, the beads that hold one)."""

from __future__ import annotations

import numpy as np

#: Without a given level, this many pixels sharing the image's maximum show clipping.
MIN_CLIPPED = 3


def saturated_cores(image: np.ndarray, positions: np.ndarray, psf_radius: float,
                    level: float) -> np.ndarray:
    """Which beads have a pixel at or above ``level`` in their core (the square of half
    side ``max(1, round(r / 3))`` about each position), shape (K,), bool."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    if len(pos) == 0:
        return np.zeros(0, bool)
    h, w = image.shape
    iy = np.clip(np.round(pos[:, 0]).astype(int), 0, h - 1)
    ix = np.clip(np.round(pos[:, 1]).astype(int), 0, w - 1)
    core = max(1, int(round(psf_radius / 3)))
    d = np.arange(-core, core + 1)
    rows = np.clip(iy[:, None, None] + d[None, :, None], 0, h - 1)
    cols = np.clip(ix[:, None, None] + d[None, None, :], 0, w - 1)
    return image[rows, cols].reshape(len(pos), -1).max(axis=1) >= level


def saturation_record(image: np.ndarray, beads, psf_radius: float,
                      level: float | None) -> dict:
    """What a reader must be told of saturation: the level (the given one, else the
    image's maximum where it is the dtype's or :data:`MIN_CLIPPED` pixels or more share
    it, else the dtype's maximum for integer images), the pixels at it and the
    detections whose core holds one (whatever else left them out)."""
    img = np.asarray(image)
    if level is None:
        top = float(img.max())
        n_top = int(np.count_nonzero(img >= top))
        dtype_max = float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else None
        # a camera clips below its container's maximum too (12 bits in 16): pixels
        # sharing the image's maximum are clipped
        level = top if (top == dtype_max or n_top >= MIN_CLIPPED) else (
            dtype_max if dtype_max is not None else top)
    n_pix = int(np.count_nonzero(img >= level))
    if n_pix < MIN_CLIPPED and level == float(img.max()) and img.dtype.kind not in "ui":
        n_pix = 0  # a float image's brightest pixel or two: no clipping shown
    n_beads = int(saturated_cores(img, beads.positions, psf_radius, level).sum()) \
        if n_pix else 0
    return {"level": float(level), "pixels": n_pix, "beads": n_beads,
            "detections": int(len(beads.positions))}


__all__ = ["MIN_CLIPPED", "saturated_cores", "saturation_record"]
