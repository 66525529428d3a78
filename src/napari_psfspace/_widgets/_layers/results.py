"""Result layers: a model, a family, held-out residuals, a PSF, the patch gallery, as
layer-data tuples laid out in the slots of :mod:`.frame`."""

from __future__ import annotations

import numpy as np

from ...core.common.mosaic import mosaic
from .figure import colorbar_layers, map_layers, titles_layer
from .frame import Frame, LayerTuple, beside
from .names import (
    BASIS,
    FAMILY_TITLES,
    GALLERY,
    HELDOUT_LAYER,
    MAPS,
    MODEL_TITLES,
    OPERATOR_KEY,
    PSF_AT,
    PSF_GRID,
    SUB_BASIS,
    SUB_CONDITIONS,
    SUB_GRID,
    SUB_SPACE,
    SUBSPACE_KEY,
)


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
    s_mosaic = min(frame.height, frame.width) / tiles.shape[0]
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
        (by, bx, f"PSF basis: {basis.shape[0]} PSFs"),
        (my, mx, f"weight maps\nfield {_length(frame.shape[1], frame, 0)}"),
    ], frame)
    return [
        *map_layers(m_tiles, {
            "name": MAPS, "scale": (m_scale, m_scale), "translate": (my, mx),
            "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
            "metadata": {"about": f"alpha_i: weight of h_i over the image, each scaled to "
                                  f"its largest magnitude, i = 0.. left to right, "
                                  f"{m_cols} a row"}}, "", frame),
        *map_layers(tiles.astype(np.float32), {
            "name": PSF_GRID, "scale": (s_mosaic, s_mosaic), "translate": (y0, x0),
            "colormap": "magma", "contrast_limits": (0.0, 1.0), "metadata": meta}, "", frame),
        *map_layers(b_tiles, {
            "name": BASIS, "scale": (b_scale, b_scale), "translate": (by, bx),
            "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
            "metadata": {"about": f"orthonormal PSF basis h_i, each scaled to its largest "
                                  f"magnitude, i = 0.. left to right, {b_cols} a row"}},
            "", frame),
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


def family_layers(sub, ys: np.ndarray, xs: np.ndarray, psfs: np.ndarray,
                    coords: np.ndarray, frame: Frame, *,
                    stack_axis: tuple[float, float] = (0.0, 1.0)) -> list[LayerTuple]:
    """Layer-data tuples showing a family of operators.

    Parameters
    ----------
    sub : OperatorFamily
    ys, xs, psfs
        :meth:`OperatorFamily.psf_grids`: psfs of shape (K, n, n, P, P).
    coords : ndarray of shape (K, 2)
        :meth:`OperatorFamily.condition_coordinates`.
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
    # inside the box, a tenth of it below its title
    points = np.stack([cy + 0.55 * box - c[:, 1] / span * 0.45 * box,
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
        (sy, sx, f"{space.shape[0]} spatial maps"),  # short: the slots are narrow
        (y0, x0, f"PSF grid {len(ys)} x {len(xs)}"),
        (by, bx, f"PSF basis: {basis.shape[0]}"),
        (cy, cx, "conditions"),
    ], frame)
    return [
        *map_layers(s_tiles, {
            "name": SUB_SPACE, "scale": (s_scale, s_scale), "translate": (sy, sx),
            "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
            "metadata": {"about": f"a_j: the family's spatial basis over the field (coarse "
                                  f"grid), each scaled to its largest magnitude, j = 0.. "
                                  f"left to right, {s_cols} a row"}}, "", frame),
        *map_layers(tiles.astype(np.float32), {
            "name": SUB_GRID, "scale": (float(stack_axis[1]), s_mosaic, s_mosaic),
            "translate": (float(stack_axis[0]), y0, x0),
            "colormap": "magma", "contrast_limits": (0.0, 1.0),
            "metadata": {SUBSPACE_KEY: sub, "psf_grid_rows": np.asarray(ys).tolist(),
                         "psf_grid_columns": np.asarray(xs).tolist(), "images": images,
                         "about": "PSF of each image's operator at field positions, each "
                                  "scaled to its maximum, gamma 0.5 (slider: image)"}},
            "", frame),
        *map_layers(b_tiles, {
            "name": SUB_BASIS, "scale": (b_scale, b_scale), "translate": (by, bx),
            "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
            "metadata": {"about": f"orthonormal PSF basis h_i of the family, each scaled to "
                                  f"its largest magnitude, i = 0.. left to right, {b_cols} "
                                  f"a row"}}, "", frame),
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


def heldout_layers(heldout, frame: Frame) -> list[LayerTuple]:
    """Points at the held-out beads, coloured by their residual (``HeldoutResiduals``),
    and the colour bar of that residual right of the image."""
    residual = np.asarray(heldout.residual, float)
    features = {"residual": residual,
                "noise_floor": np.asarray(heldout.noise_floor, float)}
    finite = residual[np.isfinite(residual)]
    lim = ((float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0))
    if lim[1] <= lim[0]:
        lim = (lim[0], lim[0] + max(abs(lim[0]), 1e-6))
    points = (np.asarray(heldout.positions, float),
              {"name": HELDOUT_LAYER, "features": features, "scale": frame.scale,
               "translate": frame.translate, "size": 20, "symbol": "square",
               "face_color": "residual", "face_colormap": "plasma",
               "face_contrast_limits": lim, "border_width": 0, "opacity": 0.6},
              "points")
    slot = (frame.translate[0] - frame.scale[0] / 2, frame.translate[1] - frame.scale[1] / 2,
            frame.height, frame.width)
    return [points, *colorbar_layers(HELDOUT_LAYER, "", "plasma", lim, slot, frame)]


def psf_layers(psf: np.ndarray, y: float, x: float, frame: Frame) -> list[LayerTuple]:
    """The PSF at pixel (y, x) as an image layer (saved as TIFF by the plugin's writer),
    with its colour bar."""
    y0, x0 = beside(frame, 2.0, 1.0)
    s = 0.45 * frame.height / psf.shape[-1]
    psf = np.asarray(psf, np.float32)
    return map_layers(psf,
            {"name": PSF_AT, "scale": (s, s), "translate": (y0, x0), "colormap": "magma",
             "contrast_limits": (0.0, float(max(psf.max(), 1e-12))),
             "metadata": {"pixel_size_um": frame.pixel_size, "psf_row": float(y),
                          "psf_column": float(x)}}, "", frame)


def gallery_layers(stack: np.ndarray, frame: Frame, *, view: str) -> list[LayerTuple]:
    """The patches (K, P, P) as one 2-D mosaic below the image (near-square grid, bead
    ``k`` at row ``k // columns``, column ``k % columns``; :func:`gallery_cell`), each
    patch scaled to its largest magnitude: no axis shared with the data; then its
    colour bar's layers."""
    y0, x0 = beside(frame, 0.0, 1.0)
    tiles, scale, cols = _flat_mosaic(stack, frame, 1.0, gap=GALLERY_GAP)
    lim = (min(float(tiles.min()), 0.0), max(float(tiles.max()), 1e-12))
    return map_layers(tiles, {
        "name": GALLERY, "scale": (scale, scale), "translate": (y0, x0),
        "colormap": "gray", "contrast_limits": lim,
        "metadata": {"view": view, "columns": cols, "patch": stack.shape[-1],
                     "about": f"bead patches ({view}), bead 1.. left to right, {cols} a "
                              f"row"}}, "", frame)


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

