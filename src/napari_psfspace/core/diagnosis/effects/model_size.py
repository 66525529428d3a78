"""A PSF basis or a field model too small for what the beads show."""

from __future__ import annotations

from .base import Context, Effect


class BasisSize(Effect):
    """Two more PSF basis elements than the model has (coherent residual structure)."""

    name = "basis_size"
    description = "PSF basis too small (two more basis PSFs)"
    tests = ("coherent_residual", "mean_residual")

    def applicable(self, ctx: Context) -> bool:
        return ctx.params.get("_model", {}).get("n_psf", 0) + 2 <= 16

    def fit(self, ctx: Context, analysis) -> dict:
        return {"n_psf": int(ctx.params.get("_model", {}).get("n_psf", 1)) + 2}

    def apply(self, ctx: Context, params: dict) -> Context:
        est = {**ctx.estimate_kwargs, "n_psf": params["n_psf"]}
        return ctx.with_effect(self.name, params, estimate_kwargs=est)


class FieldSmoothing(Effect):
    """Less smoothing of the coefficient maps (residual trends across the field)."""

    name = "field_smoothing"
    description = "field model too smooth (thin-plate smoothing divided by 10)"
    tests = ("trend_radius", "trend_row", "trend_column")

    def fit(self, ctx: Context, analysis) -> dict:
        current = ctx.params.get("_model", {}).get("smoothing") or [1e-3]
        return {"smoothing": float(min(current)) / 10.0}

    def apply(self, ctx: Context, params: dict) -> Context:
        est = {**ctx.estimate_kwargs, "smoothing": params["smoothing"]}
        return ctx.with_effect(self.name, params, estimate_kwargs=est)
