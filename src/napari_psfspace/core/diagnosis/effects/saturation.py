"""Detector saturation: pixels at the clipping level carry no shape information.

Saturated pixels are *censored*: their true value is at least the clipping level. The
effect masks them in every bead fit and fills them, for learning the PSF, with the value
a model learnt from the unsaturated beads predicts (never below the level), so that the
bright beads' wings still train the model instead of the bright beads being dropped
(which, when most beads saturate, leaves too few to learn from).
"""

from __future__ import annotations

import numpy as np

from ...beads.centering import gather_windows
from ...beads.detect import KEPT
from ...common.progress import run_with_progress
from ...model.estimate import iter_estimate
from ..residuals import fit_beads
from .base import Context, Effect


def impute_clipped(ctx: Context, level: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The image with clipped pixels near beads replaced by a model's prediction.

    Returns the new image (M, N), the mask of clipped pixels (M, N) and the number of
    beads touched.
    """
    image = ctx.image
    clipped = image >= level
    beads = ctx.beads
    est = run_with_progress(iter_estimate(
        image, psf_radius=ctx.psf_radius, beads=beads, holdout=None,
        **{**ctx.estimate_kwargs, "saturation": level}))
    op = est.operator
    half = op.psf_size // 2
    kept = np.flatnonzero(beads.status == KEPT)
    touched = kept[gather_windows(clipped, np.round(beads.positions[kept]), half)
                   .any(axis=(1, 2))]
    out = image.copy()
    if len(touched):
        fit_kw = {k: v for k, v in ctx.fit_kwargs.items() if k != "response"}
        res = fit_beads(image, beads.positions[touched], op, ctx.noise,
                        pixel_mask=ctx.pixel_mask | clipped, **fit_kw)
        base = np.round(beads.positions[touched]).astype(int)
        h, w = image.shape
        for k, (cy, cx) in enumerate(base):
            y0, x0 = cy - half, cx - half
            ys = slice(max(y0, 0), min(y0 + 2 * half + 1, h))
            xs = slice(max(x0, 0), min(x0 + 2 * half + 1, w))
            pred = res.model[k][ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0]
            sub = out[ys, xs]
            c = clipped[ys, xs]
            sub[c] = np.maximum(pred[c], level)
    return out, clipped, int(len(touched))


class Saturation(Effect):
    """Mask saturated pixels in the fits; fill them from a model to learn the PSF."""

    name = "saturation"
    description = ("detector saturation (clipped pixels masked in the fits and filled from "
                   "a model of the unsaturated beads to learn the PSF)")
    tests = ("saturation",)

    def fit(self, ctx: Context, analysis) -> dict:
        level = float(analysis.tests["saturation"].detail["level"])
        return {"level": level, "pixels": int(np.count_nonzero(ctx.image >= level))}

    def apply(self, ctx: Context, params: dict) -> Context:
        level = params["level"]
        try:
            image, clipped, n = impute_clipped(ctx, level)
        except ValueError:  # too few unsaturated beads to learn from: mask and drop them
            est = {**ctx.estimate_kwargs, "saturation": level}
            return ctx.with_effect(self.name, {**params, "filled_beads": 0},
                                   pixel_mask=ctx.pixel_mask | (ctx.image >= level),
                                   estimate_kwargs=est)
        return ctx.with_effect(self.name, {**params, "filled_beads": n}, image=image,
                               pixel_mask=ctx.pixel_mask | clipped)



