"""Hot pixels and other isolated outlier pixels: mask them, inpaint the image."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from ..analysis import _pixel_outliers
from .base import Context, Effect


class OutlierPixels(Effect):
    """Single pixels far above all their neighbours (hot pixels, cosmic rays)."""

    name = "outlier_pixels"
    description = "hot pixels / outlier pixels (masked, inpainted with the local median)"
    tests = ("pixel_outliers",)

    def fit(self, ctx: Context, analysis) -> dict:
        found = _pixel_outliers(ctx.image, ctx.noise)
        return {"count": found["count"], "positions": found["positions"]}

    def apply(self, ctx: Context, params: dict) -> Context:
        mask = np.zeros(ctx.image.shape, bool)
        pos = np.asarray(params["positions"], dtype=int).reshape(-1, 2)
        mask[pos[:, 0], pos[:, 1]] = True
        image = ctx.image.copy()
        med = ndi.median_filter(ctx.image, size=3, mode="nearest")
        image[mask] = med[mask]
        return ctx.with_effect(self.name, params, image=image,
                               pixel_mask=ctx.pixel_mask | mask,
                               noise=ctx.renoised(image))
