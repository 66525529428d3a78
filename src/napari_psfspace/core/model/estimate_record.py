"""The records an estimate keeps in its operator's metadata: the basis and the field
chosen, the detections left out and why, and the hot pixels masked. JSON-ready."""

from __future__ import annotations

import numpy as np

from ..beads.detect import Beads
from .pca import PsfBasis


def basis_record(basis: PsfBasis, n_psf, spline, smoothing, few) -> dict:
    """The metadata of the basis and the field: sizes asked and chosen, smoothing, degrees
    of freedom, and the few-bead model when there is one."""
    return {
        "n_psf": basis.n_psf,
        "n_psf_rule": basis.n_psf_rule,
        "n_psf_requested": n_psf,
        "heldout_error_by_n_psf": (None if basis.heldout_errors is None
                                   else [float(v) for v in basis.heldout_errors]),
        "smoothing": None if spline is None else [float(s) for s in spline.smoothing],
        "smoothing_requested": smoothing,
        "effective_dof": None if spline is None else [float(d) for d in spline.effective_dof],
        "field_dof": None if spline is None else field_dof_record(spline),
        "field_model": "thin-plate" if few is None else few.field_model,
        "field_model_reason": None if few is None else few.reason,
        "few_beads_loo_errors": None if few is None else few.metadata()["loo_errors"],
    }


#: Why a detection of each status is not used, for :func:`left_out_record`.
STATUS_REASONS = {
    "saturated": "saturated pixels in its core",
    "border": "too close to the image border for its patch",
    "neighbour": "another detection within 2 PSF radii",
    "faint": "too faint to shape the PSF",
    "outlier": "its shape is unlike what its neighbours predict (held-out error)",
    "rejected": "rejected by the user",
    "companion": "a companion inside its patch",
    "structure": "background structure, not a bead",
}


def field_dof_record(spline) -> dict:
    """JSON-ready record of how rich the thin-plate field is, and why (see
    :class:`~napari_psfspace.core.model.tps.ThinPlateSpline`'s ``max_dof``)."""
    dof = [float(d) for d in spline.effective_dof]
    richer = [int(i) for i in np.flatnonzero(spline.richer)]
    rec = {"limit": None if spline.max_dof is None else float(spline.max_dof),
           "samples": int(spline.n_nodes), "max": float(max(dof)) if dof else 0.0,
           "richer": richer}
    if richer:
        gain = ", ".join(f"{100 * spline.loo_gain[i]:.0f} %" for i in richer)
        rec["note"] = (f"the field of {len(richer)} basis coefficient(s) uses more than half "
                       f"as many degrees of freedom as beads ({rec['max']:.1f} for "
                       f"{rec['samples']}): held-out beads show the richer field predicts "
                       f"them better (leave-one-out error {gain} lower, at least "
                       "2 standard errors)")
    return rec


def left_out_record(beads: Beads, reasons: dict[int, str] | None = None,
                    limit: int = 500) -> dict:
    """JSON-ready record of the detections not used and why: counts by status and, for
    up to ``limit`` of them, ``{"position", "status", "why"}``."""
    reasons = reasons or {}
    out = np.flatnonzero(~np.isin(beads.status, ("kept", "heldout")))
    counts: dict[str, int] = {}
    items = []
    for i in out:
        st = str(beads.status[i])
        counts[st] = counts.get(st, 0) + 1
        if len(items) < limit:
            items.append({"position": [round(float(v), 2) for v in beads.positions[i]],
                          "status": st,
                          "why": reasons.get(int(i), STATUS_REASONS.get(st, st))})
    return {"counts": counts, "beads": items}


def hot_pixel_record(pixels, limit: int = 10_000) -> dict:
    """JSON-ready record of the masked hot pixels: their count and (up to ``limit``)
    ``(row, column)`` positions."""
    pix = np.zeros((0, 2), int) if pixels is None else np.asarray(pixels).reshape(-1, 2)
    return {"count": int(len(pix)), "positions": pix[:limit].astype(int).tolist()}
