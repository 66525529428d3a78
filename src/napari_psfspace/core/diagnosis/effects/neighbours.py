"""Neighbouring beads merged with the bead by the detector: fitted jointly."""

from __future__ import annotations

import numpy as np

from ...beads.detect import COMPANION, NEIGHBOUR
from ..residuals import BeadResiduals, fourier_shift
from .base import Context, Effect

#: Companion offsets searched around a stretched bead, pixels: from 0.75 to 3.5 px (a
#: companion 1-3 px away merges with its bead; closer, the two are one spot), on a grid
#: of 0.25 px.
_STEP, _MIN_SEP, _MAX_SEP = 0.25, 0.75, 3.5
_GRID = np.arange(-_MAX_SEP, _MAX_SEP + 1e-9, _STEP)
OFFSETS = np.array([(dy, dx) for dy in _GRID for dx in _GRID
                    if _MIN_SEP <= np.hypot(dy, dx) <= _MAX_SEP])


def locate_companion(res: BeadResiduals, i: int) -> tuple[float, float] | None:
    """Offset ``(dy, dx)`` (pixels, from the bead's position) of a companion merged with
    bead ``i``: the one of :data:`OFFSETS` whose joint fit (the bead's model PSF at the
    bead and at the offset, each with a positive amplitude, and a constant background)
    leaves the smallest weighted residual on the bead's fit disk, refined to 0.05 px
    around it (a grid point's error left a doublet's residual for a per-bead size to
    explain); ``None`` when no offset gives two positive amplitudes. The model PSF does
    not change over 3.5 px."""
    msk = res.fit_mask[i]
    d = res.data[i][msk]
    h = (res.model[i] - res.background[i]) / max(float(res.amplitude[i]), 1e-300)
    w = 1.0 / np.sqrt(np.maximum(res.variance[i][msk], 1e-300))
    one = np.ones(d.size)

    def search(offsets, best, where):
        shifted = fourier_shift(np.repeat(h[None], len(offsets), axis=0), offsets)[:, msk]
        for k, s in enumerate(shifted):
            x = np.stack([h[msk], s, one], axis=1)
            c = np.linalg.lstsq(x * w[:, None], d * w, rcond=None)[0]
            if c[0] <= 0 or c[1] <= 0:
                continue
            sse = float(np.sum(((d - x @ c) * w) ** 2))
            if sse < best:
                best, where = sse, (float(offsets[k, 0]), float(offsets[k, 1]))
        return best, where

    best, where = search(OFFSETS, np.inf, None)
    if where is not None:  # then to 0.05 px around the best grid point
        fine = np.arange(-_STEP, _STEP + 1e-9, _STEP / 5)
        local = np.array([(where[0] + a, where[1] + b) for a in fine for b in fine])
        best, where = search(local, best, where)
    return where


class Neighbours(Effect):
    """Beads with a companion in their patch: the companion is fitted jointly (its own
    amplitude, the model's PSF at its position) and the bead no longer trains the model
    (status "companion"); it is still judged, so the error is compared on the same beads.
    A companion so close that it lies inside the core (the bead is stretched, test
    ``elongated_beads``) is located by a joint two-source fit of the bead's patch
    (:func:`locate_companion`) and then fitted jointly the same way; a stretched bead
    whose patch gives no such fit is set aside (status "neighbour": neither learnt from
    nor judged). Setting every stretched bead aside instead thins the field's sampling:
    on bright family scenes the typical bead improved while the mean error rose."""

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
            # a companion 1-3 px away, inside the core: located by a joint fit of the
            # bead's residual entry (``beads``: residual rows, ``bead_index``: the table)
            detail = analysis.tests["elongated_beads"].detail
            rows = np.asarray(detail.get("beads", []), dtype=int)
            index = np.asarray(detail.get("bead_index", []), dtype=int)
            res = analysis.residuals
            beads, comps, left = list(out["beads"]), list(out["companions"]), []
            taken = set(beads)
            for j, i in sorted(zip(rows.tolist(), index.tolist(), strict=True),
                               key=lambda t: t[1]):
                if i in taken:
                    continue
                q = locate_companion(res, j) if res is not None else None
                if q is None:
                    left.append(int(i))
                    continue
                beads.append(int(i))
                comps.append([float(res.positions[j][0] + q[0]),
                              float(res.positions[j][1] + q[1])])
            out.update(beads=beads, companions=comps, stretched=left)
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
