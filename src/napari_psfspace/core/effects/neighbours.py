"""Neighbouring beads merged with the bead by the detector: fitted jointly."""

from __future__ import annotations

import numpy as np

from ..detect import COMPANION
from .base import Context, Effect


class Neighbours(Effect):
    """Beads with a companion in their patch: the companion is fitted jointly (its own
    amplitude, the model's PSF at its position) and the bead no longer trains the model
    (status "companion"); it is still judged, so the error is compared on the same beads."""

    name = "neighbours"
    description = ("companion beads inside the patch (fitted jointly; such beads no longer "
                   "used to learn the PSF)")
    tests = ("secondary_peaks",)

    def fit(self, ctx: Context, analysis) -> dict:
        detail = analysis.tests["secondary_peaks"].detail
        index = np.asarray(detail.get("bead_index", []), dtype=int)
        peaks = np.asarray(detail.get("peaks", []), dtype=float).reshape(-1, 2)
        return {"beads": index.tolist(), "companions": peaks.tolist(),
                "count": int(len(index))}

    def apply(self, ctx: Context, params: dict) -> Context:
        beads = ctx.beads
        index = np.asarray(params["beads"], dtype=int)
        status = beads.status.copy()
        status[index] = COMPANION
        new = beads.copy(status)
        companions = dict(ctx.fit_kwargs.get("companions", {}))
        for i, peak in zip(index, params["companions"], strict=True):
            key = tuple(int(v) for v in np.round(beads.positions[i]))
            companions.setdefault(key, []).append(tuple(peak))
        fit = {**ctx.fit_kwargs, "companions": companions}
        return ctx.with_effect(self.name, params, beads=new, fit_kwargs=fit)
