"""Result layers: a model, a family, held-out residuals, a PSF, the patch gallery, as
layer-data tuples on the image's field (:func:`.frame.on_field`)."""

from __future__ import annotations

import numpy as np

from ..core.common.mosaic import mosaic
from .figure import OVERLAYS_KEY, finite_limits, map_tuple
from .frame import Frame, LayerTuple, field_units, on_field
from .names import (
    BASIS,
    BEAD_FWHM,
    GALLERY,
    HELDOUT_LAYER,
    OPERATOR_KEY,
    PSF_AT,
    PSF_GRID,
    SUB_BASIS,
    SUB_GRID,
    SUB_SPACE,
    SUBSPACE_KEY,
    WEIGHT,
)

#: Weight maps shown when a model is learnt; the others are made hidden (each hidden
#: layer takes no cell of napari's grid), to be shown from the layer list.
SHOWN_WEIGHTS = 3
#: Largest side of a weight map shown (a smooth map: every few pixels suffice).
WEIGHT_SIDE = 512


def operator_layers(op, frame: Frame, *, grid: int = 8) -> list[LayerTuple]:
    """Layer-data tuples showing a model: PSF grid mosaic, PSF basis mosaic and one
    weight map a basis PSF, each on the image's field.

    Parameters
    ----------
    op : ProductConvolution
    frame : Frame
        The image's frame (the layers lie on its field).
    grid : int
        The PSF mosaic shows ``grid x grid`` field positions.

    Returns
    -------
    list of (data, kwargs, layer_type)
        The PSF-grid layer's metadata holds the operator under :data:`OPERATOR_KEY`,
        which the model writer saves.
    """
    ys, xs, psfs = op.psf_grid(grid, grid)
    tiles = mosaic(psfs, gap=1, normalize="each", gamma=0.5).astype(np.float32)
    meta = {OPERATOR_KEY: op, "pixel_size_um": frame.pixel_size,
            "psf_grid_rows": ys.tolist(), "psf_grid_columns": xs.tolist(),
            "about": f"PSF at {grid} x {grid} field positions, tiles of "
                     f"{_length(op.psf_size, frame)}, each scaled to its maximum, gamma 0.5. "
                     "Save this layer as .npz to save the model."}
    basis = np.asarray(op.basis, np.float32)
    out = [
        map_tuple(tiles, {"name": PSF_GRID, **on_field(frame, tiles.shape, fill=1.0),
                          "colormap": "magma", "contrast_limits": (0.0, 1.0),
                          "metadata": meta}, "", frame),
        _basis_tuple(basis, BASIS, "", frame),
    ]
    if op.n_psf == 1:  # one PSF everywhere: no weight varies over the field
        return out
    maps = op.coefficient_maps()
    step = max(1, int(np.ceil(max(maps.shape[1:]) / WEIGHT_SIDE)))
    for i, m in enumerate(maps[:, ::step, ::step]):
        m = np.asarray(m, np.float64)
        top = float(np.abs(m).max()) or 1.0
        out.append(map_tuple((m / top).astype(np.float32), {
            "name": WEIGHT.format(i + 1), **on_field(frame, m.shape, fill=1.0),
            "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
            "visible": i < SHOWN_WEIGHTS,
            "metadata": {"about": f"weight of basis PSF {i + 1} over the field, scaled to "
                                  f"its largest magnitude; every {step} px"}}, "", frame))
    return out


def _basis_tuple(basis: np.ndarray, name: str, whose: str, frame: Frame) -> LayerTuple:
    """A PSF basis (I, P, P) as one mosaic layer on the field, each PSF scaled to its
    largest magnitude."""
    tiles, cols = _flat_mosaic(basis, gap=2)
    return map_tuple(tiles, {
        "name": name, **on_field(frame, tiles.shape, fill=1.0),
        "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
        "metadata": {"about": f"orthonormal PSF basis{whose}, {basis.shape[0]} PSFs, each "
                              f"scaled to its largest magnitude, 1.. left to right, {cols} "
                              f"a row"}}, "", frame)


def _length(pixels: float, frame: Frame, digits: int = 2) -> str:
    """``pixels`` as a length: in µm when the frame is calibrated, else in px."""
    if frame.pixel_size:
        return f"{pixels * frame.pixel_size:.{digits}f} µm"
    return f"{pixels:g} px"


def _flat_mosaic(stack: np.ndarray, *, gap: int) -> tuple[np.ndarray, int]:
    """``(tiles, columns)``: a stack (K, P, Q) as one 2-D image (near-square grid, each
    tile scaled to its largest magnitude)."""
    stack = np.asarray(stack, np.float64)
    tiles = mosaic(stack, gap=gap, normalize="each", fill=0.0).astype(np.float32)
    return tiles, int(np.ceil(np.sqrt(stack.shape[0])))


def family_layers(sub, ys: np.ndarray, xs: np.ndarray, psfs: np.ndarray, frame: Frame, *,
                  stack_axis: tuple[float, float] = (0.0, 1.0)) -> list[LayerTuple]:
    """Layer-data tuples showing a family of operators, each on one image's field.

    Parameters
    ----------
    sub : OperatorFamily
    ys, xs, psfs
        :meth:`OperatorFamily.psf_grids`: psfs of shape (K, n, n, P, P).
    frame : Frame
        One image's frame.
    stack_axis : (float, float)
        World position and step of the PSF-grid stack's first axis: for a z-stack's
        slices, those of the first slice learnt from, so that the z slider shows each
        slice with its own PSF grid.

    Returns
    -------
    list of (data, kwargs, layer_type)
        The PSF grid of each image as a stack (slider: image), the family's PSF basis
        and its spatial maps, as mosaics. The PSF-grid layer's metadata holds the
        family under :data:`SUBSPACE_KEY`. The conditions are a table in the dock.
    """
    images = [int(i) for i in sub.metadata.get("images", range(sub.n_images))]
    one = [mosaic(p, gap=1, normalize="each", gamma=0.5) for p in psfs]
    tiles = np.zeros((max(images) + 1, *one[0].shape), np.float32)  # a skipped image: empty
    tiles[images] = one
    grid = on_field(frame, tiles.shape, fill=1.0)
    basis = np.asarray(sub.basis, np.float32)
    space = np.asarray(sub.space, np.float32)
    s_tiles, s_cols = _flat_mosaic(space, gap=1)
    return [
        map_tuple(tiles, {
            "name": SUB_GRID, "scale": (float(stack_axis[1]), *grid["scale"]),
            "translate": (float(stack_axis[0]), *grid["translate"]),
            "colormap": "magma", "contrast_limits": (0.0, 1.0),
            "metadata": {SUBSPACE_KEY: sub, "psf_grid_rows": np.asarray(ys).tolist(),
                         "psf_grid_columns": np.asarray(xs).tolist(), "images": images,
                         "about": f"PSF of each image's operator at {len(ys)} x {len(xs)} "
                                  "field positions, each scaled to its maximum, gamma 0.5 "
                                  "(slider: image)"}}, "", frame),
        _basis_tuple(basis, SUB_BASIS, " of the family", frame),
        map_tuple(s_tiles, {
            "name": SUB_SPACE, **on_field(frame, s_tiles.shape, fill=1.0),
            "colormap": "twilight_shifted", "contrast_limits": (-1.0, 1.0),
            "metadata": {"about": f"the family's {space.shape[0]} spatial maps over the "
                                  f"field (coarse grid), each scaled to its largest "
                                  f"magnitude, 1.. left to right, {s_cols} a row"}},
            "", frame),
    ]


def heldout_layers(heldout, frame: Frame) -> list[LayerTuple]:
    """Squares at the held-out beads on the image's field, coloured by their residual
    (``HeldoutResiduals``), shown with their colour bar in a cell of their own."""
    residual = np.asarray(heldout.residual, float)
    features = {"residual": residual,
                "noise_floor": np.asarray(heldout.noise_floor, float)}
    lim = finite_limits(residual)
    return [(np.asarray(heldout.positions, float),
             {"name": HELDOUT_LAYER, "features": features, "scale": frame.scale,
              "translate": frame.translate, **field_units(frame), "size": 20,
              "symbol": "square", "face_color": "residual", "face_colormap": "plasma",
              "face_contrast_limits": lim, "border_width": 0,
              "metadata": {OVERLAYS_KEY: {"unit": ""},
                           "about": "held-out residual of each bead, in fraction of its "
                                    "energy"}},
             "points")]


def bead_fwhm_layer(positions: np.ndarray, fwhm_px: np.ndarray, frame: Frame) -> LayerTuple:
    """Each bead's own lateral FWHM as a point at the bead, coloured by it, in µm where
    the image is calibrated (else px): the field as the beads show it, for a model of
    one PSF that does not map it."""
    scale = frame.pixel_size or 1.0
    unit = "µm" if frame.pixel_size else "px"
    values = np.asarray(fwhm_px, float) * scale
    ok = np.isfinite(values)  # a bead whose patch is no spot has no FWHM: not drawn
    positions = np.asarray(positions, float).reshape(-1, 2)[ok]
    values = values[ok]
    lim = finite_limits(values)
    return (positions,
            {"name": f"{BEAD_FWHM} ({unit})", "features": {"fwhm": values},
             "scale": frame.scale, "translate": frame.translate, **field_units(frame),
             "size": 0.04 * max(frame.shape), "face_color": "fwhm",
             "face_colormap": "viridis", "face_contrast_limits": lim, "border_width": 0,
             "metadata": {OVERLAYS_KEY: {"unit": unit},
                          "about": f"each bead's own lateral FWHM (Gaussian fit of its "
                                   f"patch): the model is one PSF and maps no field; "
                                   f"{int((~ok).sum())} bead(s) not a spot, not drawn"}},
            "points")


def psf_layers(psf: np.ndarray, y: float, x: float, frame: Frame) -> list[LayerTuple]:
    """The PSF at pixel (y, x) as an image layer on the field, magnified (saved as TIFF
    by the plugin's writer)."""
    psf = np.asarray(psf, np.float32)
    return [map_tuple(psf, {
        "name": PSF_AT, **on_field(frame, psf.shape, fill=1.0), "colormap": "magma",
        "contrast_limits": (0.0, float(max(psf.max(), 1e-12))),
        "metadata": {"pixel_size_um": frame.pixel_size, "psf_row": float(y),
                     "psf_column": float(x),
                     "about": f"PSF at row {y:.0f}, column {x:.0f}, magnified"}}, "", frame)]


def gallery_layers(stack: np.ndarray, frame: Frame, *, view: str) -> list[LayerTuple]:
    """The patches (K, P, P) as one 2-D mosaic right of the image, as large as its field
    (near-square grid, bead ``k`` at row ``k // columns``, column ``k % columns``;
    :func:`gallery_cell`), each patch scaled to its largest magnitude: beside the
    image, where a click picks a bead while the image stays in view."""
    tiles, cols = _flat_mosaic(stack, gap=GALLERY_GAP)
    lim = (min(float(tiles.min()), 0.0), max(float(tiles.max()), 1e-12))
    place = on_field(frame, tiles.shape, fill=1.0)
    ty, tx = place["translate"]
    place["translate"] = (ty, tx + GALLERY_SHIFT * frame.width)
    return [map_tuple(tiles, {
        "name": GALLERY, **place,
        "colormap": "gray", "contrast_limits": lim,
        "metadata": {"view": view, "columns": cols, "patch": stack.shape[-1],
                     "about": f"bead patches ({view}), bead 1.. left to right, {cols} a "
                              f"row"}}, "", frame)]


#: Pixels between the gallery's patches.
GALLERY_GAP = 2
#: The gallery's offset right of the image, in fractions of the field's width.
GALLERY_SHIFT = 1.1


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

