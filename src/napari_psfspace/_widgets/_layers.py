"""Conversions between napari layers and the core's objects.

Layer data travel as napari *layer-data tuples* ``(data, kwargs, layer_type)``, so this
module imports neither napari nor Qt (the model reader uses it too). Layers are read
duck-typed (``layer.data``, ``layer.scale``, ``layer.features``).

Layout of the result layers in world coordinates (the image's units), so that nothing
hides anything else and nothing shares the data's axes (every result is 2-D, a labelled
mosaic, except the family's PSF grids, one per image of a stack, which follow the
stack's own slider)::

    row 0  [ image (+ diagnosis maps) ] [ PSF grid          ] [ PSF basis h_i ]
    row 1  [ patch gallery (Review)   ] [ coefficient maps  ] [ PSF at (y, x) ]
    row 2  [ family's spatial basis   ] [ family's PSF grid ] [ family's h_i  ] [ conditions ]
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.beads.detect import (
    COMPANION,
    HELDOUT,
    KEPT,
    OUTLIER,
    REJECTED,
    STATUSES,
    STRUCTURE,
    Beads,
)
from ..core.common.mosaic import mosaic

#: Every status a bead of the Points layer can have ("rejected": by the user in the
#: review; not used for the model).
ALL_STATUSES = STATUSES
#: Ring colour of each status in the Points layer.
STATUS_COLORS = {
    "kept": "#3cff3c",
    "saturated": "#ff9900",
    "border": "#ffe135",
    "neighbour": "#29c8ff",
    "faint": "#a0a0a0",
    "outlier": "#ff40ff",
    REJECTED: "#ff2020",
    HELDOUT: "#ffffff",
    COMPANION: "#8a2be2",
    STRUCTURE: "#8b5a2b",
}
#: Human-readable meaning of each status (shown in the widgets).
STATUS_MEANING = {
    "kept": "kept",
    "saturated": "saturated",
    "border": "too close to the border",
    "neighbour": "too close to a neighbour",
    "faint": "no signal above the background",
    "outlier": "z-score outlier",
    REJECTED: "rejected by hand",
    HELDOUT: "held out of the fit",
    COMPANION: "companion in the patch (fitted jointly, not learnt)",
    STRUCTURE: "background structure, not a bead (wider than the PSF)",
}
#: Names of the layers the plugin creates.
BEADS = "beads"
GALLERY = "bead patches"
CURRENT = "patch on display"
PSF_GRID = "PSF grid"
BASIS = "PSF basis h_i"
MAPS = "coefficient maps alpha_i"
HELDOUT = "held-out split: residual per bead"
PSF_AT = "PSF at position"
SUB_GRID = "subspace PSF grid"
SUB_BASIS = "subspace PSF basis h_i"
SUB_SPACE = "subspace spatial basis a_j"
SUB_CONDITIONS = "subspace conditions"
MODEL_TITLES = "titles: model"
FAMILY_TITLES = "titles: family"
#: Key of the subspace layer metadata that holds the OperatorSubspace.
SUBSPACE_KEY = "psfspace_subspace"
HOT_PIXELS = "hot pixels"
#: Key of the layer metadata that holds the operator (read by the model writer).
OPERATOR_KEY = "psfspace_operator"

LayerTuple = tuple[Any, dict, str]


@dataclass(frozen=True)
class Frame:
    """Where an image lies in world coordinates.

    Attributes
    ----------
    shape : tuple of int
        (rows, columns) of the image plane.
    scale : tuple of float
        World units per pixel along rows and columns (micrometres when known).
    translate : tuple of float
        World position of pixel (0, 0).
    index : int or None
        Slice of a 3-D stack the plane was taken from (None for a 2-D image).
    """

    shape: tuple[int, int]
    scale: tuple[float, float] = (1.0, 1.0)
    translate: tuple[float, float] = (0.0, 0.0)
    index: int | None = None  # slice of a stack the plane was taken from

    @property
    def height(self) -> float:
        return self.shape[0] * self.scale[0]

    @property
    def width(self) -> float:
        return self.shape[1] * self.scale[1]

    @property
    def pixel_size(self) -> float | None:
        """Pixel size in micrometres, or None for a unit (uncalibrated) scale."""
        return None if np.allclose(self.scale, 1.0) else float(self.scale[-1])


def image_plane(layer, world_point=None, *, index: int | None = None
                ) -> tuple[np.ndarray, Frame]:
    """The 2-D plane of an image layer and its frame, as plain values.

    Parameters
    ----------
    layer : napari.layers.Image
        A 2-D image, or a 3-D stack (Z, Y, X) of which the slice at ``world_point`` is taken.
    world_point : sequence of float, optional
        The viewer's current point (``viewer.dims.point``), used for stacks.
    index : int, optional
        Slice of a stack to take; overrides ``world_point``.

    Returns
    -------
    plane : ndarray of shape (M, N)
        A copy, safe to hand to a worker thread.
    frame : Frame

    Raises
    ------
    ValueError
        An RGB image, or more than 3 dimensions.
    """
    if getattr(layer, "rgb", False):
        raise ValueError(f"Layer {layer.name!r} is an RGB image: choose a single-channel "
                         "bead image (split the channels first).")
    data = np.asarray(layer.data)
    scale, translate = np.asarray(layer.scale, float), np.asarray(layer.translate, float)
    z = None
    if data.ndim == 3:
        z = 0 if index is None else int(index)
        if index is None and world_point is not None:
            z = int(round((float(world_point[-3]) - translate[0]) / scale[0]))
        z = int(np.clip(z, 0, data.shape[0] - 1))
        data = data[z]
    elif data.ndim != 2:
        raise ValueError(f"Layer {layer.name!r} has {data.ndim} dimensions: choose a 2-D "
                         "bead image or a 3-D stack (Z, Y, X).")
    frame = Frame(tuple(data.shape), tuple(scale[-2:].tolist()), tuple(translate[-2:].tolist()),
                  z)
    return np.array(data, copy=True), frame


def bead_plane(image_layer, points_layer, world_point=None) -> tuple[np.ndarray, Frame]:
    """The plane the beads of a Points layer were detected on.

    The Points layer is the truth: when it was made from this image (its metadata
    names the image and the slice), that slice is used, whatever the viewer's sliders
    show (a patch gallery or basis stack shares the first axis with a z-stack).
    """
    meta = getattr(points_layer, "metadata", None) or {}
    index = meta.get("slice") if meta.get("image") == image_layer.name else None
    return image_plane(image_layer, world_point, index=index)


# ------------------------------------------------------------------ beads <-> Points
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
              "size": 3.0, "symbol": "x", "face_color": "#ff2020", "border_width": 0,
              "opacity": 0.9}
    return np.asarray(pixels, dtype=float).reshape(-1, 2), kwargs, "points"


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


# ------------------------------------------------------------------ results
def _gap(frame: Frame) -> float:
    """World distance between two slots of the layout."""
    return 0.04 * max(frame.height, frame.width)


def beside(frame: Frame, column: float, row: float = 0.0) -> tuple[float, float]:
    gap = _gap(frame)
    return (frame.translate[0] + row * (frame.height + gap),
            frame.translate[1] + column * (frame.width + gap))


def operator_layers(op, frame: Frame, *, grid: int = 8) -> list[LayerTuple]:
    """Layer-data tuples showing a model: PSF grid mosaic, basis stack, coefficient maps.

    Parameters
    ----------
    op : ProductConvolution
    frame : Frame
        The image's frame (the maps get its scale and position).
    grid : int
        The PSF mosaic shows ``grid x grid`` field positions.

    Returns
    -------
    list of (data, kwargs, layer_type)
        The PSF-grid layer's metadata holds the operator under :data:`OPERATOR_KEY`,
        which the model writer saves.
    """
    ys, xs, psfs = op.psf_grid(grid, grid)
    tiles = mosaic(psfs, gap=1, normalize="each", gamma=0.5)
    s_mosaic = frame.height / tiles.shape[0]
    y0, x0 = beside(frame, 1.0)
    meta = {OPERATOR_KEY: op, "pixel_size_um": frame.pixel_size,
            "psf_grid_rows": ys.tolist(), "psf_grid_columns": xs.tolist(),
            "about": f"PSF at {grid}x{grid} field positions, each scaled to its maximum, "
                     "gamma 0.5. Save this layer as .npz to save the model."}
    basis = np.asarray(op.basis, np.float32)
    b_tiles, b_scale, b_cols = _flat_mosaic(basis, frame, 0.9, gap=2)
    by, bx = beside(frame, 2.0)
    maps = op.coefficient_maps()
    step = int(np.ceil(np.sqrt(maps.shape[0])))  # smooth maps: every step-th pixel
    m_tiles, m_scale, m_cols = _flat_mosaic(maps[:, ::step, ::step], frame, 1.0, gap=4)
    my, mx = beside(frame, 1.0, 1.0)
    psf_um = _length(op.psf_size, frame)
    titles = titles_layer(MODEL_TITLES, [
        (y0, x0, f"PSF grid {grid} x {grid}\ntiles {psf_um}"),
        (by, bx, f"basis h_0..h_{basis.shape[0] - 1}"),
        (my, mx, f"maps alpha_i\nfield {_length(frame.shape[1], frame, 0)}"),
    ], frame)
    return [
        (m_tiles, {"name": MAPS, "scale": (m_scale, m_scale), "translate": (my, mx),
                   "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
                   "metadata": {"about": f"alpha_i: weight of h_i over the image, each "
                                         f"scaled to its largest magnitude, i = 0.. left "
                                         f"to right, {m_cols} a row"}},
         "image"),
        (tiles.astype(np.float32), {"name": PSF_GRID, "scale": (s_mosaic, s_mosaic),
                                    "translate": (y0, x0), "colormap": "magma",
                                    "metadata": meta}, "image"),
        (b_tiles, {"name": BASIS, "scale": (b_scale, b_scale), "translate": (by, bx),
                   "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
                   "metadata": {"about": f"orthonormal PSF basis h_i, each scaled to its "
                                         f"largest magnitude, i = 0.. left to right, "
                                         f"{b_cols} a row"}}, "image"),
        titles,
    ]


def _length(pixels: float, frame: Frame, digits: int = 2) -> str:
    """``pixels`` as a length: in µm when the frame is calibrated, else in px."""
    if frame.pixel_size:
        return f"{pixels * frame.pixel_size:.{digits}f} µm"
    return f"{pixels:g} px"


def _flat_mosaic(stack: np.ndarray, frame: Frame, fill: float, *, gap: int
                 ) -> tuple[np.ndarray, float, int]:
    """``(tiles, scale, columns)``: a stack (K, P, Q) as one 2-D image (near-square grid,
    each tile scaled to its largest magnitude), and the world scale per pixel that fits
    it in ``fill`` of one slot of the layout (the image's size): it never reaches into
    the next slot."""
    stack = np.asarray(stack, np.float64)
    tiles = mosaic(stack, gap=gap, normalize="each", fill=0.0).astype(np.float32)
    cols = int(np.ceil(np.sqrt(stack.shape[0])))
    scale = fill * min(frame.height / tiles.shape[0], frame.width / tiles.shape[1])
    return tiles, float(scale), cols


def subspace_layers(sub, ys: np.ndarray, xs: np.ndarray, psfs: np.ndarray,
                    coords: np.ndarray, frame: Frame, *,
                    stack_axis: tuple[float, float] = (0.0, 1.0)) -> list[LayerTuple]:
    """Layer-data tuples showing a family of operators.

    Parameters
    ----------
    sub : OperatorSubspace
    ys, xs, psfs
        :meth:`OperatorSubspace.psf_grids`: psfs of shape (K, n, n, P, P).
    coords : ndarray of shape (K, 2)
        :meth:`OperatorSubspace.condition_coordinates`.
    frame : Frame
        One image's frame (the spatial basis gets its scale and position).
    stack_axis : (float, float)
        World position and step of the PSF-grid stack's first axis: for a z-stack's
        slices, those of the first slice learnt from, so that the z slider shows each
        slice with its own PSF grid.

    Returns
    -------
    list of (data, kwargs, layer_type)
        The PSF grid of each image as a stack (slider: image), the PSF basis ``h_i``,
        the spatial basis ``a_j`` on the image, and the images' conditions as points
        beside the grid. The PSF-grid layer's metadata holds the subspace under
        :data:`SUBSPACE_KEY`.
    """
    images = [int(i) for i in sub.metadata.get("images", range(sub.n_images))]
    one = [mosaic(p, gap=1, normalize="each", gamma=0.5) for p in psfs]
    tiles = np.zeros((max(images) + 1, *one[0].shape))  # a skipped image: an empty slice
    tiles[images] = one
    s_mosaic = frame.height / tiles.shape[1]
    y0, x0 = beside(frame, 1.0, 2.0)
    basis = np.asarray(sub.basis, np.float32)
    b_tiles, b_scale, b_cols = _flat_mosaic(basis, frame, 0.9, gap=2)
    by, bx = beside(frame, 2.0, 2.0)
    space = np.asarray(sub.space, np.float32)
    s_tiles, s_scale, s_cols = _flat_mosaic(space, frame, 1.0, gap=1)
    sy, sx = beside(frame, 0.0, 2.0)
    box = 0.45 * frame.height
    c = np.asarray(coords, float)[:, :2]
    span = float(np.abs(c).max()) or 1.0
    cy, cx = beside(frame, 3.0, 2.0)
    points = np.stack([cy + box / 2 - c[:, 1] / span * box / 2,
                       cx + box / 2 + c[:, 0] / span * box / 2], axis=1)
    held = sub.metadata.get("heldout") or []
    residual = np.array([h.get("residual_mean", np.nan) if h.get("n_beads") else np.nan
                         for h in held] if len(held) == sub.n_images
                        else [np.nan] * sub.n_images, float)
    labels = sub.metadata.get("labels") or [str(i) for i in images]
    # on the canvas, a stack slice's number ("stack[12]" -> "12") or the layer's name
    short = [lab.rsplit("[", 1)[-1].rstrip("]") if lab.endswith("]") else lab
             for lab in labels]
    titles = titles_layer(FAMILY_TITLES, [
        (sy, sx, f"family\na_0..a_{space.shape[0] - 1}"),
        (y0, x0, f"PSF grid {len(ys)} x {len(xs)}\nper image"),
        (by, bx, f"family\nh_0..h_{basis.shape[0] - 1}"),
        (cy, cx, "conditions\n(Gamma_k)"),
    ], frame)
    return [
        (s_tiles, {"name": SUB_SPACE, "scale": (s_scale, s_scale), "translate": (sy, sx),
                   "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
                   "metadata": {"about": f"a_j: the family's spatial basis over the field "
                                         f"(coarse grid), each scaled to its largest "
                                         f"magnitude, j = 0.. left to right, {s_cols} a "
                                         f"row"}}, "image"),
        (tiles.astype(np.float32), {
            "name": SUB_GRID, "scale": (float(stack_axis[1]), s_mosaic, s_mosaic),
            "translate": (float(stack_axis[0]), y0, x0),
            "colormap": "magma",
            "metadata": {SUBSPACE_KEY: sub, "psf_grid_rows": np.asarray(ys).tolist(),
                         "psf_grid_columns": np.asarray(xs).tolist(), "images": images,
                         "about": "PSF of each image's operator at field positions, each "
                                  "scaled to its maximum, gamma 0.5 (slider: image)"}},
         "image"),
        (b_tiles, {"name": SUB_BASIS, "scale": (b_scale, b_scale), "translate": (by, bx),
                   "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
                   "metadata": {"about": f"orthonormal PSF basis h_i of the family, each "
                                         f"scaled to its largest magnitude, i = 0.. left "
                                         f"to right, {b_cols} a row"}}, "image"),
        (points, {"name": SUB_CONDITIONS, "size": 0.03 * frame.height,
                  "features": {"image": np.asarray(images, int), "label": list(labels),
                               "short": short,
                               "heldout": residual},
                  "text": {"string": "{short}", "size": 9, "color": "white"},
                  "face_color": "#29c8ff", "border_width": 0,
                  "metadata": {"about": "conditions: first two principal coordinates of "
                                        "the Gamma_k (label: the image)",
                               "coordinates": c.tolist()}},
         "points"),
        titles,  # last: drawn over the mosaics
    ]


def heldout_layer(heldout, frame: Frame) -> LayerTuple:
    """Points at the held-out beads, coloured by their residual (``HeldoutResiduals``)."""
    features = {"residual": np.asarray(heldout.residual, float),
                "noise_floor": np.asarray(heldout.noise_floor, float)}
    return (np.asarray(heldout.positions, float),
            {"name": HELDOUT, "features": features, "scale": frame.scale,
             "translate": frame.translate, "size": 20, "symbol": "square",
             "face_color": "residual", "face_colormap": "plasma", "border_width": 0,
             "opacity": 0.6},
            "points")


def psf_layer(psf: np.ndarray, y: float, x: float, frame: Frame) -> LayerTuple:
    """The PSF at pixel (y, x) as an image layer (saved as TIFF by the plugin's writer)."""
    y0, x0 = beside(frame, 2.0, 1.0)
    s = 0.45 * frame.height / psf.shape[-1]
    return (np.asarray(psf, np.float32),
            {"name": PSF_AT, "scale": (s, s), "translate": (y0, x0), "colormap": "magma",
             "metadata": {"pixel_size_um": frame.pixel_size, "psf_row": float(y),
                          "psf_column": float(x)}}, "image")


def gallery_layer(stack: np.ndarray, frame: Frame, *, view: str) -> LayerTuple:
    """The patches (K, P, P) as one 2-D mosaic below the image (near-square grid, bead
    ``k`` at row ``k // columns``, column ``k % columns``; :func:`gallery_cell`), each
    patch scaled to its largest magnitude: no axis shared with the data."""
    y0, x0 = beside(frame, 0.0, 1.0)
    tiles, scale, cols = _flat_mosaic(stack, frame, 1.0, gap=GALLERY_GAP)
    return (tiles, {"name": GALLERY, "scale": (scale, scale), "translate": (y0, x0),
                    "colormap": "gray",
                    "metadata": {"view": view, "columns": cols, "patch": stack.shape[-1],
                                 "about": f"bead patches ({view}), bead 1.. left to right, "
                                          f"{cols} a row"}}, "image")


#: Pixels between the gallery's patches.
GALLERY_GAP = 2


def gallery_cell(layer, k: int) -> np.ndarray:
    """The world corners ``[[y0, x0], [y1, x1]]`` of patch ``k`` in the gallery layer."""
    meta = layer.metadata
    cols, p = int(meta["columns"]), int(meta["patch"])
    step = p + GALLERY_GAP
    r, c = divmod(int(k), cols)
    scale, origin = np.asarray(layer.scale, float), np.asarray(layer.translate, float)
    lo = origin + scale * np.array([r * step, c * step], float) - scale / 2
    return np.stack([lo, lo + scale * p])


def gallery_index(layer, world: np.ndarray) -> int | None:
    """The patch of the gallery under a world position, or None between patches."""
    meta = layer.metadata
    cols, p = int(meta["columns"]), int(meta["patch"])
    step = p + GALLERY_GAP
    pix = (np.asarray(world, float)[-2:] - np.asarray(layer.translate, float)) / np.asarray(
        layer.scale, float) + 0.5
    if np.any(pix < 0):
        return None
    r, c = (int(v) for v in pix // step)
    if c >= cols or np.any(pix % step >= p):
        return None
    return r * cols + c


#: Metadata key marking a layer the plugin made, with the name it asked for: found again
#: on a re-run even when napari renamed it ("beads [1]" beside a user's image "beads").
MADE_AS = "psfspace_layer"


def _kind(layer) -> str:
    # ``__class__``, not ``type()``: through napari's Plugins menu the viewer is a
    # ``PublicOnlyProxy``, whose layers' ``type()`` is the proxy's
    return layer.__class__.__name__.lower()


def find_layer(viewer, name: str, kind: str | None = None):
    """The plugin's layer made as ``name`` (see :data:`MADE_AS`), else the layer of that
    name (of ``kind`` when given), else None."""
    for layer in viewer.layers:
        if (layer.metadata or {}).get(MADE_AS) == name and kind in (None, _kind(layer)):
            return layer
    if name in viewer.layers and kind in (None, _kind(viewer.layers[name])):
        return viewer.layers[name]
    return None


#: Metadata key of the step that made a layer: a step's layers are one group, replaced
#: together on a re-run and removed together (:func:`remove_step`).
STEP_KEY = "psfspace_step"
#: Key of a layer-data tuple's kwargs (not napari's): show the layer's colour bar.
COLORBAR = "colorbar"


def step_layers(viewer, step: str) -> list:
    """The layers the plugin made for ``step`` (its group)."""
    return [layer for layer in viewer.layers if (layer.metadata or {}).get(STEP_KEY) == step]


def remove_step(viewer, step: str) -> int:
    """Remove the layers of one step's group, its titles included; how many went."""
    gone = step_layers(viewer, step)
    for layer in gone:
        viewer.layers.remove(layer)
    return len(gone)


def show_layers(viewer, tuples: list[LayerTuple], *, step: str | None = None,
                replace: bool = False) -> list:
    """Add the layers to the viewer, or update in place those the plugin made under the
    same name (whatever napari renamed them to).

    ``step`` tags the layers as that step's group; with ``replace``, the group's layers
    this call does not make again are removed (a re-run leaves the same layer set, never
    a stale title or map of the run before). A tuple whose kwargs hold
    ``colorbar=True`` (:data:`COLORBAR`) gets its colour bar shown."""
    out = []
    names = set()
    for data, kwargs, kind in tuples:
        name = kwargs["name"]
        names.add(name)
        bar = bool(kwargs.get(COLORBAR, False))
        meta = {**(kwargs.get("metadata") or {}), MADE_AS: name}
        if step is not None:
            meta[STEP_KEY] = step
        kwargs = {k: v for k, v in kwargs.items() if k != COLORBAR} | {"metadata": meta}
        layer = find_layer(viewer, name, kind)
        if layer is not None:
            if np.ndim(layer.data) != np.ndim(data) and kind == "image":
                viewer.layers.remove(layer)
                layer = None
            else:
                _update(layer, data, {k: v for k, v in kwargs.items() if k != "name"})
        if layer is None:
            layer = getattr(viewer, f"add_{kind}")(data, **kwargs)
        if bar and hasattr(layer, "colorbar"):
            layer.colorbar.visible = True
        out.append(layer)
    if step is not None and replace:
        for layer in step_layers(viewer, step):
            if (layer.metadata or {}).get(MADE_AS) not in names:
                viewer.layers.remove(layer)
    return out


def below_others(viewer, frame: Frame, row: float, step: str) -> Frame:
    """``frame`` moved down so that its result row ``row`` starts below every layer of
    the viewer outside ``step``'s group: results laid out from another image's frame
    (a family learnt from a stack beside a model learnt from one image) never land on
    the other results."""
    bottom = -np.inf
    for layer in viewer.layers:
        if (layer.metadata or {}).get(STEP_KEY) == step:
            continue
        bottom = max(bottom, float(np.asarray(layer.extent.world)[1][-2]))
    top = beside(frame, 0.0, row)[0]
    shift = max(0.0, bottom + _gap(frame) - top) if np.isfinite(bottom) else 0.0
    return Frame(frame.shape, frame.scale, (frame.translate[0] + shift, frame.translate[1]),
                 frame.index)


def titles_layer(name: str, entries: list[tuple[float, float, str]], frame: Frame
                 ) -> LayerTuple:
    """A points layer whose texts title the result slots: ``entries`` of (world row,
    world column, text), each text anchored at that position, the slot's top-left
    corner (napari draws it just inside the slot). Titles are short
    (the canvas shows three slots side by side); each layer's ``metadata["about"]`` says
    the rest."""
    pos = np.array([[y, x] for y, x, _ in entries], float).reshape(-1, 2)
    lift = 0.012 * max(frame.height, frame.width)
    return (pos - [lift, 0.0],
            {"name": name, "features": {"title": [t for _, _, t in entries]},
             "text": {"string": "{title}", "size": 8, "color": "white",
                      "anchor": "lower_left"},
             "size": 0.001 * max(frame.height, frame.width), "face_color": "transparent",
             "border_width": 0, "metadata": {"about": "titles of the result mosaics"}},
            "points")


def _update(layer, data, kwargs: dict) -> None:
    if "metadata" in kwargs:  # before the data: listeners of data events read it
        layer.metadata = kwargs["metadata"]
    if "features" in kwargs:  # points: data and features must change together
        layer.data = data
        layer.features = kwargs["features"]
    else:
        layer.data = data
    for key in ("scale", "translate", "metadata", "contrast_limits"):
        if key in kwargs:
            setattr(layer, key, kwargs[key])
    if "contrast_limits" not in kwargs and hasattr(layer, "reset_contrast_limits"):
        layer.reset_contrast_limits()
    if hasattr(layer, "refresh_colors"):
        layer.refresh_colors()
