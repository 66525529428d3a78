"""Neighbouring beads merged with the bead by the detector: fitted jointly."""

from __future__ import annotations

import numpy as np

from ..detect import COMPANION, NEIGHBOUR
from .base import Context, Effect


class Neighbours(Effect):
    """Beads with a companion in their patch: the companion is fitted jointly (its own
    amplitude, the model's PSF at its position) and the bead no longer trains the model
    (status "companion"); it is still judged, so the error is compared on the same beads.
    A companion so close that it lies inside the core (the bead is stretched, test
    ``elongated_beads``) is not fitted jointly: the bead is set aside (status
    "neighbour": neither learnt from nor judged)."""

    name = "neighbours"
    description = ("companion beads inside the patch (fitted jointly; such beads no longer "
                   "used to learn the PSF)")
    tests = ("secondary_peaks", "elongated_beads")

    def fit(self, ctx: Context, analysis) -> dict:
        out = {"beads": [], "companions": [], "stretched": []}
        if "secondary_peaks" in analysis.tests:
            detail = analysis.tests["secondary_peaks"].detail
            index = np.asarray(detail.get("bead_index", []), dtype=int)
            peaks = np.asarray(detail.get("peaks", []), dtype=float).reshape(-1, 2)
            out.update(beads=index.tolist(), companions=peaks.tolist())
        if "elongated_beads" in analysis.tests:
            # a companion 1-3 px away, inside the core: where exactly is not known well
            # enough to fit it jointly
            detail = analysis.tests["elongated_beads"].detail
            index = np.asarray(detail.get("bead_index", []), dtype=int)
            out["stretched"] = sorted(set(index.tolist()) - set(out["beads"]))
        out["count"] = len(out["beads"]) + len(out["stretched"])
        return out

    def apply(self, ctx: Context, params: dict) -> Context:
        beads = ctx.beads
        index = np.asarray(params["beads"], dtype=int)
        status = beads.status.copy()
        status[index] = COMPANION
        # a stretched bead is two beads the model cannot fit as one: neither learnt
        # from nor judged (the comparison is then on the beads both models judge)
        status[np.asarray(params.get("stretched", []), dtype=int)] = NEIGHBOUR
        new = beads.copy(status)
        companions = dict(ctx.fit_kwargs.get("companions", {}))
        for i, peak in zip(index, params["companions"], strict=True):
            key = tuple(int(v) for v in np.round(beads.positions[i]))
            companions.setdefault(key, []).append(tuple(peak))
        fit = {**ctx.fit_kwargs, "companions": companions}
        return ctx.with_effect(self.name, params, beads=new, fit_kwargs=fit)
