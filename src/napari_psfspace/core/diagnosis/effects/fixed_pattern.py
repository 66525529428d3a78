"""Fixed-pattern offsets of the camera: one offset per row and per column."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from ..background_tests import bead_free_mask, smooth_background
from .base import Context, Effect


def line_offsets(image: np.ndarray, free: np.ndarray, psf_radius: float, axis: int
                 ) -> np.ndarray:
    """Offset of each row (axis=1) or column (axis=0): the median of the bead-free,
    detrended pixels of the line minus the mean of its +-4 neighbours' medians."""
    level = smooth_background(image, free, sigma=max(8.0, 2 * psf_radius))
    med = np.nanmedian(np.where(free, image - level, np.nan), axis=axis)
    med = np.where(np.isfinite(med), med, 0.0)
    kern = np.ones(9) / 8.0
    kern[4] = 0.0
    return med - ndi.convolve1d(med, kern, mode="reflect")


class FixedPattern(Effect):
    """Row and column offsets (sCMOS/CCD readout pattern), subtracted from the image."""

    name = "fixed_pattern"
    description = "fixed-pattern row / column offsets of the camera (subtracted)"
    tests = ("row_pattern", "column_pattern")
    own_evidence = True

    def fit(self, ctx: Context, analysis) -> dict:
        free = bead_free_mask(ctx.image.shape, ctx.beads.positions, ctx.psf_radius)
        free &= ~ctx.pixel_mask
        rows = line_offsets(ctx.image, free, ctx.psf_radius, axis=1)
        cols = line_offsets(ctx.image, free, ctx.psf_radius, axis=0)
        use_rows = analysis.tests["row_pattern"].significant
        use_cols = analysis.tests["column_pattern"].significant
        return {"rows": rows.round(4).tolist() if use_rows else None,
                "columns": cols.round(4).tolist() if use_cols else None,
                "rms_rows": float(np.std(rows)), "rms_columns": float(np.std(cols))}

    def apply(self, ctx: Context, params: dict) -> Context:
        image = ctx.image.copy()
        if params.get("rows") is not None:
            image -= np.asarray(params["rows"])[:, None]
        if params.get("columns") is not None:
            image -= np.asarray(params["columns"])[None, :]
        return ctx.with_effect(self.name, params, image=image, noise=ctx.renoised(image))
