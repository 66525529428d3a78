"""Non-uniform illumination: the optics' throughput varies smoothly over the field."""

from __future__ import annotations

import numpy as np

from ..analysis import THRESHOLDS
from ..photometry import crossfit_log_residuals, throughput_at
from ..statistics import radial_trend
from .base import Context, Effect


class Illumination(Effect):
    """A smooth throughput ``t(x)`` (log-quadratic in the field position) fitted to the
    beads' amplitudes; the operator's PSFs then integrate to ``t(x)`` (normalised to a
    field mean of 1) instead of 1.

    The PSF *shapes* do not change (each bead's amplitude is fitted freely), so the
    shape error cannot drop: the held-out error this effect lowers is the photometric
    one, the mean squared log ratio of each bead's amplitude to the throughput predicted
    by the other folds (:func:`~napari_psfspace.core.diagnosis.photometry.crossfit_log_residuals`).
    """

    name = "illumination"
    description = ("non-uniform illumination / vignetting (a smooth throughput over the "
                   "field, from the beads' brightness)")
    tests = ("amplitude_field",)
    degree = 2

    def applicable(self, ctx: Context) -> bool:
        return super().applicable(ctx) and ctx.throughput_degree < self.degree

    def fit(self, ctx: Context, analysis) -> dict:
        detail = analysis.tests["amplitude_field"].detail
        coef = np.asarray(detail["coefficients"], dtype=np.float64)
        h, w = ctx.image.shape
        corners = np.array([[0, 0], [0, w - 1], [h - 1, 0], [h - 1, w - 1],
                            [(h - 1) / 2, (w - 1) / 2]], dtype=np.float64)
        t = throughput_at(coef, corners, ctx.image.shape)
        return {"degree": self.degree, "coefficients": coef.round(5).tolist(),
                "corner_over_centre": (t[:4] / t[4]).round(4).tolist()}

    def apply(self, ctx: Context, params: dict) -> Context:
        return ctx.with_effect(self.name, params, throughput_degree=int(params["degree"]))

    def reading_after(self, test: str, after, ctx: Context, cf) -> float | None:
        """The radial trend's z (:func:`~..statistics.radial_trend`) in the beads'
        held-out amplitude ratios to the throughput fitted without their fold: the
        residual analysis fits each bead's amplitude freely and reads the raw
        amplitudes, which no throughput changes. One-sided, as the test: held-out
        ratios of a throughput that follows the beads keep less radial trend than
        chance would (F below 1, z negative), which reads 0."""
        if test != "amplitude_field":
            return super().reading_after(test, after, ctx, cf)
        res = cf.residuals
        logs = crossfit_log_residuals(res.positions, res.amplitude, cf.fold,
                                      ctx.image.shape, degree=ctx.throughput_degree,
                                      use=res.photometric)
        ok = np.isfinite(logs) & res.photometric
        if ok.sum() < 12:
            return None
        z = radial_trend(res.positions[ok], np.exp(logs[ok]), ctx.image.shape,
                         THRESHOLDS[test])["z"]
        return max(z, 0.0)

