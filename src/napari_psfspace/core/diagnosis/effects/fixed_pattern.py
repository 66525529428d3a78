"""Fixed-pattern offsets of the camera: one offset per row and per column."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from ...beads.noise import NoiseModel
from ..background_tests import NEIGHBOURS, bead_free_mask, line_levels, smooth_background
from .base import Context, Effect

#: passes of the neighbour filter: the offsets are the line levels less their
#: ``SMOOTHING``-fold neighbour mean, a low-pass of about ``sqrt(15 SMOOTHING)`` lines'
#: width, where one pass leaves an eighth of white offsets' variance for the
#: pattern test to read.
SMOOTHING = 8


def line_offsets(image: np.ndarray, free: np.ndarray, psf_radius: float, axis: int,
                 noise: NoiseModel) -> np.ndarray:
    """Offset of each row (axis=1) or column (axis=0), ADU, shape (n_lines,): the line
    level of the bead-free, detrended pixels (the pattern test's clipped mean,
    :func:`~..background_tests.line_levels`) less its smooth part, the neighbour mean
    of :func:`~..background_tests.line_pattern` applied ``SMOOTHING`` times. Lines
    without enough bead-free pixels get 0."""
    level = smooth_background(image, free, sigma=max(8.0, 2 * psf_radius))
    d = line_levels(image - level, level, free, noise, axis)
    ok = d["ok"]
    out = np.zeros(len(ok))
    if ok.sum() < 10:
        return out
    m = d["mean"][ok]
    smooth = m.copy()
    for _ in range(SMOOTHING):
        smooth = ndi.convolve1d(smooth, NEIGHBOURS, mode="reflect")
    out[ok] = m - smooth
    return out


class FixedPattern(Effect):
    """Row and column offsets (sCMOS/CCD readout pattern), subtracted from the image."""

    name = "fixed_pattern"
    description = "fixed-pattern row / column offsets of the camera (subtracted)"
    tests = ("row_pattern", "column_pattern")
    own_evidence = True

    def fit(self, ctx: Context, analysis) -> dict:
        free = bead_free_mask(ctx.image.shape, ctx.beads.positions, ctx.psf_radius)
        free &= ~ctx.pixel_mask
        rows = line_offsets(ctx.image, free, ctx.psf_radius, 1, ctx.noise)
        cols = line_offsets(ctx.image, free, ctx.psf_radius, 0, ctx.noise)
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
