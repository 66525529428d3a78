"""The coordinate frame: where an image lies in world coordinates, and where its results
lie.

Every result lies on the image's field (:func:`on_field`): napari's grid puts each
beside the image, in its own cell, with its name and colour bar (:mod:`.figure`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

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
    units : str or None
        The unit of the image's axes as napari holds it (``layer.units``), or None for
        pixels: its results get the same, so that napari's scale bar reads it.
    """

    shape: tuple[int, int]
    scale: tuple[float, float] = (1.0, 1.0)
    translate: tuple[float, float] = (0.0, 0.0)
    index: int | None = None  # slice of a stack the plane was taken from
    units: str | None = None

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
                  z, axis_unit(layer))
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

# ------------------------------------------------------------------ results
def on_field(frame: Frame, shape, *, fill: float | None = None) -> dict:
    """``scale`` and ``translate`` that put an array of ``shape`` (rows, columns) on the
    image's field, centred: every result lies where the image lies, so napari's grid
    shows each beside the image at the same place of the field, and the camera's zoom
    and pan act on all of them at once.

    Parameters
    ----------
    frame : Frame
    shape : (int, int)
        Rows and columns of the result.
    fill : float, optional
        None: at the image's pixel scale (a map on the image's own pixels, shrunk only
        where it is larger than the field). Else the fraction of the field the result
        fills (a mosaic of small patches, magnified to be read).

    Returns
    -------
    dict
        ``{"scale": (sy, sx), "translate": (ty, tx)}`` for the layer's kwargs.
    """
    shape = np.asarray(shape, float)[-2:]
    size = np.array([frame.height, frame.width])
    pixel = np.asarray(frame.scale, float)
    if fill is None:
        factor = min(1.0, float(np.min(size / (shape * pixel))))
    else:
        factor = float(fill) * float(np.min(size / (shape * pixel)))
    scale = pixel * factor
    corner = np.asarray(frame.translate, float) - pixel / 2  # the field's top-left corner
    top_left = corner + (size - shape * scale) / 2
    return {"scale": tuple(scale.tolist()), "translate": tuple((top_left + scale / 2).tolist())}


def axis_unit(layer) -> str | None:
    """The unit of a layer's last axis as napari holds it (``layer.units``), or None
    for pixels (napari's default) or a layer without units."""
    units = getattr(layer, "units", None)
    if not units:
        return None
    unit = str(units[-1])
    return None if unit in ("pixel", "px", "") else unit


def field_units(frame: Frame, ndim: int = 2) -> dict:
    """``{"units": ...}`` for a result's kwargs: the image's unit on every axis (napari
    draws a scale bar in one unit only when every layer shown has it), else nothing."""
    return {"units": (frame.units,) * ndim} if frame.units else {}
