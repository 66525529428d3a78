"""Detector saturation: pixels at the clipping level carry no shape information."""

from __future__ import annotations

import numpy as np

from .base import Context, Effect


class Saturation(Effect):
    """Mask saturated pixels in the fits and keep saturated beads out of the PSF."""

    name = "saturation"
    description = "detector saturation (saturated pixels masked, their beads not learnt)"
    tests = ("saturation",)

    def fit(self, ctx: Context, analysis) -> dict:
        level = float(analysis.tests["saturation"].detail["level"])
        return {"level": level, "pixels": int(np.count_nonzero(ctx.image >= level))}

    def apply(self, ctx: Context, params: dict) -> Context:
        level = params["level"]
        est = {**ctx.estimate_kwargs, "saturation": level}
        return ctx.with_effect(self.name, params, pixel_mask=ctx.pixel_mask
                               | (ctx.image >= level), estimate_kwargs=est)
