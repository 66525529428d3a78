"""Bead points: detected beads <-> a napari Points layer, coloured by status, and the
pixels masked as hot pixels."""

from __future__ import annotations

import numpy as np

from ..core.beads.detect import HELDOUT, KEPT, OUTLIER, Beads
from .bookkeeping import find_layer
from .figure import OVERLAYS_KEY
from .frame import Frame, LayerTuple, field_units
from .names import ALL_STATUSES, BEADS, HOT_PIXELS, LEFT_OUT, MORE_BEADS, STATUS_COLORS


def beads_layer(beads: Beads, frame: Frame, psf_radius: float, *,
                name: str = BEADS) -> LayerTuple:
    """Points layer-data tuple of detected beads, coloured by status.

    The features are ``id`` (0..M-1), ``amplitude`` and ``status`` (categorical over
    :data:`ALL_STATUSES`); a point added by hand gets status "kept" (its id is set by
    :func:`fix_ids`).
    """
    features = {
        "id": np.arange(len(beads), dtype=np.int64),
        "amplitude": np.asarray(beads.amplitude, float),
        "status": _categorical(beads.status),
    }
    kwargs = {
        "name": name,
        "features": features,
        "feature_defaults": {"id": -1, "amplitude": np.nan, "status": KEPT},
        "scale": frame.scale,
        "translate": frame.translate,
        **field_units(frame),
        "size": 2.0 * float(psf_radius),
        "symbol": "ring",
        "face_color": "status",
        "face_color_cycle": STATUS_COLORS,
        "border_width": 0,
        "opacity": 0.9,
    }
    return beads.positions.copy(), kwargs, "points"


def hot_pixels_layer(pixels: np.ndarray, frame: Frame) -> LayerTuple:
    """Points layer-data tuple of the pixels masked as hot pixels / cosmic rays (red x)."""
    kwargs = {"name": HOT_PIXELS, "scale": frame.scale, "translate": frame.translate,
              **field_units(frame), "size": 3.0, "symbol": "x", "face_color": "#ff2020",
              "border_width": 0, "opacity": 0.9}
    return np.asarray(pixels, dtype=float).reshape(-1, 2), kwargs, "points"


def advice_layers(identification: dict, frame: Frame,
                  slice_at: tuple[float, float] | None = None) -> list[LayerTuple]:
    """Points layer-data tuples on the image an operator was identified from: where one
    more bead would help most (a yellow cross) and the clicked beads it left out (red x).

    ``slice_at``: the world (scale, translate) of the stack's axis when the image is a
    slice of one (``frame.index`` its slice), so that the points lie on that slice.
    """
    size = max(frame.shape) / 12.0  # seen at a glance over the whole image
    out = []
    for name, points, symbol, colour in (
            (MORE_BEADS, [identification.get("more_beads_at")], "cross", "#ffd400"),
            (LEFT_OUT, [e["position"] for e in identification.get("left_out") or []], "x",
             "#ff2020")):
        pts = np.asarray([p for p in points if p is not None], float).reshape(-1, 2)
        if not len(pts):
            continue
        kwargs = {"name": name, "scale": frame.scale, "translate": frame.translate,
                  **field_units(frame), "size": size, "symbol": symbol,
                  "face_color": colour, "border_width": 0, "opacity": 0.9,
                  # a cell of its own beside the image, named
                  "metadata": {OVERLAYS_KEY: {"unit": None}}}
        if frame.index is not None and slice_at is not None:
            pts = np.column_stack([np.full(len(pts), float(frame.index)), pts])
            kwargs |= {"scale": (slice_at[0], *frame.scale),
                       "translate": (slice_at[1], *frame.translate),
                       **field_units(frame, 3)}
        out.append((pts, kwargs, "points"))
    return out


def hot_pixels_from_layer(layer) -> np.ndarray:
    """The pixels (S, 2) int64 of a :func:`hot_pixels_layer` (row, column)."""
    data = np.asarray(layer.data, float).reshape(-1, np.shape(layer.data)[-1])[:, -2:]
    return np.rint(data).astype(np.int64)


def _categorical(status):
    import pandas as pd

    return pd.Categorical(np.asarray(status, dtype=str), categories=list(ALL_STATUSES))


def fix_ids(ids) -> np.ndarray:
    """Give every missing (negative, NaN) or repeated id a new one above the maximum.

    Parameters
    ----------
    ids : array_like of shape (M,)

    Returns
    -------
    ndarray of shape (M,), int64
        The first occurrence of an id keeps it.
    """
    ids = np.asarray(ids, dtype=float)
    out = np.where(np.isfinite(ids), ids, -1).astype(np.int64)
    seen: set[int] = set()
    nxt = int(out.max(initial=-1)) + 1
    for k, v in enumerate(out):
        if v < 0 or v in seen:
            out[k] = nxt
            nxt += 1
        seen.add(int(out[k]))
    return out


def beads_from_points(layer, frame: Frame) -> tuple[Beads, np.ndarray]:
    """The Points layer as a :class:`Beads` table in the image's pixel coordinates.

    Parameters
    ----------
    layer : napari.layers.Points
        Points edited by hand or not; features ``status`` (default "kept") and
        ``amplitude`` / ``id`` when present.
    frame : Frame
        The image the beads belong to (points are mapped through world coordinates,
        so a Points layer with another scale works).

    Returns
    -------
    beads : Beads
    ids : ndarray of shape (M,), int64
    """
    data = np.asarray(layer.data, float)[:, -2:]
    world = data * np.asarray(layer.scale, float)[-2:] + np.asarray(layer.translate, float)[-2:]
    pos = (world - np.asarray(frame.translate)) / np.asarray(frame.scale)
    feats = layer.features
    n = len(pos)
    status = (np.asarray(feats["status"], dtype=str) if "status" in feats
              else np.full(n, KEPT))
    status = np.where(np.isin(status, ALL_STATUSES), status, KEPT)
    amp = np.asarray(feats["amplitude"], float) if "amplitude" in feats else np.full(n, np.nan)
    ids = fix_ids(feats["id"]) if "id" in feats else np.arange(n)
    return Beads(pos, np.full(n, np.nan), status, amp), ids


#: Statuses a fit gives (its outlier rejection, its held-out split): verdicts of the
#: last run, not the user's choice. A new fit starts again from the user's selection,
#: or each re-run would drop the last run's outliers for good (fewer beads each time).
FIT_VERDICTS = (OUTLIER, HELDOUT)


def for_a_new_fit(beads: Beads) -> Beads:
    """``beads`` with the last fit's verdicts (:data:`FIT_VERDICTS`) back to "kept":
    the user's rejections and the detection's flags stay."""
    status = np.where(np.isin(beads.status, FIT_VERDICTS), KEPT, beads.status)
    return Beads(beads.positions, beads.response, status, beads.amplitude, beads.hot_pixels)


def user_beads(viewer, layer, frame: Frame) -> tuple[Beads, np.ndarray]:
    """``(beads, ids)``: the user's beads of a Points layer for a new fit
    (:func:`for_a_new_fit`), with the pixels Beads masked (its "hot pixels" layer): what
    the Model and Diagnose steps both learn from, so that they judge the same beads."""
    ensure_bead_features(layer)
    beads, ids = beads_from_points(layer, frame)
    beads = for_a_new_fit(beads)
    hot = find_layer(viewer, HOT_PIXELS, "points")
    if hot is not None:
        beads.hot_pixels = hot_pixels_from_layer(hot)
    return beads, ids


def ensure_bead_features(layer) -> None:
    """Give a Points layer made by hand the bead features (id, amplitude, status)."""
    feats = layer.features
    n = len(layer.data)
    changed = False
    if "status" not in feats:
        feats["status"] = _categorical(np.full(n, KEPT))
        changed = True
    if "amplitude" not in feats:
        feats["amplitude"] = np.full(n, np.nan)
        changed = True
    ids = fix_ids(feats["id"]) if "id" in feats else np.arange(n)
    if "id" not in feats or (ids != feats["id"].to_numpy()).any():
        feats["id"] = ids
        changed = True
    if changed:
        layer.features = feats
        layer.feature_defaults = {"id": -1, "amplitude": np.nan, "status": KEPT}


def set_statuses(layer, ids, status) -> None:
    """Set the ``status`` of the points with the given ids and refresh their colours."""
    feats = layer.features
    where = {int(v): k for k, v in enumerate(np.asarray(feats["id"]))}
    col = np.array(feats["status"], dtype=object)
    for i, s in zip(np.asarray(ids).tolist(), np.asarray(status).tolist(), strict=True):
        if int(i) in where:
            col[where[int(i)]] = str(s)
    feats["status"] = _categorical(col)
    layer.features = feats
    layer.refresh_colors(update_color_mapping=False)

