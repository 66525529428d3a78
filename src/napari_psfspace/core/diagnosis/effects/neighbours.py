"""Neighbouring beads merged with the bead by the detector: fitted jointly."""

from __future__ import annotations

import numpy as np
from scipy import optimize

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


def locate_companion(res: BeadResiduals, i: int
                     ) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """Where bead ``i`` and a companion merged with it lie: ``(shift, offset)``, pixels,
    the bead's own shift from its position and the companion's offset from the shifted
    bead; ``None`` when no offset gives two positive amplitudes.

    The joint fit is the bead's model PSF at the bead and at the companion, each with a
    positive amplitude, and a constant background, weighted on the bead's fit disk.
    The companion is first searched on :data:`OFFSETS` with the bead where it was
    detected, then both are refined together (Nelder-Mead on the four coordinates, the
    amplitudes solved at each point). The detector centres a doublet between its two
    beads, so with the bead held where it was detected the pair's residual stayed
    elongated well beyond the test's threshold. The model PSF does not change over 3.5 px."""
    msk = res.fit_mask[i]
    d = res.data[i][msk]
    h = (res.model[i] - res.background[i]) / max(float(res.amplitude[i]), 1e-300)
    w = 1.0 / np.sqrt(np.maximum(res.variance[i][msk], 1e-300))
    one = np.ones(d.size)

    def sse_of(pair):
        shifted = fourier_shift(np.repeat(h[None], 2, axis=0), pair)[:, msk]
        x = np.stack([shifted[0], shifted[1], one], axis=1)
        c = np.linalg.lstsq(x * w[:, None], d * w, rcond=None)[0]
        if c[0] <= 0 or c[1] <= 0:
            return np.inf, c
        return float(np.sum(((d - x @ c) * w) ** 2)), c

    best, where, amps = np.inf, None, None
    shifted = fourier_shift(np.repeat(h[None], len(OFFSETS), axis=0), OFFSETS)[:, msk]
    for k, comp in enumerate(shifted):
        x = np.stack([h[msk], comp, one], axis=1)
        c = np.linalg.lstsq(x * w[:, None], d * w, rcond=None)[0]
        if c[0] <= 0 or c[1] <= 0:
            continue
        sse = float(np.sum(((d - x @ c) * w) ** 2))
        if sse < best:
            best, where, amps = sse, OFFSETS[k], c
    if where is None:
        return None

    def cost(v):  # the bead within the search's reach, the pair as far apart as searched
        if np.hypot(v[0], v[1]) > _MAX_SEP or not _MIN_SEP <= np.hypot(v[2], v[3]) <= _MAX_SEP:
            return np.inf
        return sse_of(np.array([[v[0], v[1]], [v[0] + v[2], v[1] + v[3]]]))[0]

    # from the grid's pair, and from the pair centred as the detector centres it
    f = float(amps[1] / (amps[0] + amps[1]))
    starts = [np.r_[0.0, 0.0, where], np.r_[-f * where, where]]
    found = [optimize.minimize(cost, s0, method="Nelder-Mead",
                               options={"xatol": 0.01, "fatol": 1e-3, "maxiter": 400})
             for s0 in starts]
    v = min(found, key=lambda r: r.fun)
    if not np.isfinite(v.fun) or v.fun > best:
        return (0.0, 0.0), (float(where[0]), float(where[1]))
    return (float(v.x[0]), float(v.x[1])), (float(v.x[2]), float(v.x[3]))


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
    #: A few beads carry it: the held-out mean over all beads can fall by half while its
    #: test of a drop stays above the rule's p, the median bead unchanged; the beads its
    #: tests count are what the pair fit changes.
    own_evidence = True

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
            shifts = {}
            taken = set(beads)
            for j, i in sorted(zip(rows.tolist(), index.tolist(), strict=True),
                               key=lambda t: t[1]):
                if i in taken:
                    continue
                pair = locate_companion(res, j) if res is not None else None
                if pair is None:
                    left.append(int(i))
                    continue
                (sy, sx), (qy, qx) = pair
                beads.append(int(i))
                shifts[int(i)] = [sy, sx]
                comps.append([float(res.positions[j][0] + sy + qy),
                              float(res.positions[j][1] + sx + qx)])
            out.update(beads=beads, companions=comps, stretched=left, shifts=shifts)
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
        # a merged pair's bead where the joint fit put it (the detector centred the pair)
        for i, shift in (params.get("shifts") or {}).items():
            new.positions[int(i)] += np.asarray(shift, float)
        companions = dict(ctx.fit_kwargs.get("companions", {}))
        for i, peak in zip(index, params["companions"], strict=True):
            key = tuple(int(v) for v in np.round(new.positions[i]))
            companions.setdefault(key, []).append(tuple(peak))
        fit = {**ctx.fit_kwargs, "companions": companions}
        return ctx.with_effect(self.name, params, beads=new, fit_kwargs=fit)
