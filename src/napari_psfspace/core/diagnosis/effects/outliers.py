"""Hot pixels and other isolated outlier pixels: mask them, inpaint the image."""

from __future__ import annotations

import numpy as np

from ...beads.spikes import inpaint_pixels
from ..background_tests import outlier_pixels
from .base import Context, Effect


class OutlierPixels(Effect):
    """Single pixels far above all their neighbours (hot pixels, cosmic rays)."""

    name = "outlier_pixels"
    description = "hot pixels / outlier pixels (masked, inpainted with the local median)"
    tests = ("pixel_outliers",)
    own_evidence = True

    def fit(self, ctx: Context, analysis) -> dict:
        found = outlier_pixels(ctx.image, ctx.noise)
        return {"count": int(len(found)), "positions": found.tolist()}

    def apply(self, ctx: Context, params: dict) -> Context:
        mask = np.zeros(ctx.image.shape, bool)
        pos = np.asarray(params["positions"], dtype=int).reshape(-1, 2)
        mask[pos[:, 0], pos[:, 1]] = True
        image = inpaint_pixels(ctx.image, pos)
        return ctx.with_effect(self.name, params, image=image,
                               pixel_mask=ctx.pixel_mask | mask,
                               noise=ctx.renoised(image))
