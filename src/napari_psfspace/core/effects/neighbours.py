"""Neighbouring beads merged with the bead by the detector."""

from __future__ import annotations

import numpy as np

from ..detect import NEIGHBOUR
from .base import Context, Effect


class Neighbours(Effect):
    """Beads with a companion in their patch are not used (status "neighbour")."""

    name = "neighbours"
    description = "neighbouring beads inside the patch (such beads excluded)"
    tests = ("secondary_peaks",)

    def fit(self, ctx: Context, analysis) -> dict:
        detail = analysis.tests["secondary_peaks"].detail
        index = np.asarray(detail.get("bead_index", []), dtype=int)
        return {"beads": index.tolist(), "count": int(len(index))}

    def apply(self, ctx: Context, params: dict) -> Context:
        beads = ctx.beads
        status = beads.status.copy()
        status[np.asarray(params["beads"], dtype=int)] = NEIGHBOUR
        new = type(beads)(beads.positions.copy(), beads.response.copy(), status,
                          beads.amplitude.copy())
        return ctx.with_effect(self.name, params, beads=new)
