"""The coordinate frame: where an image lies in world coordinates, and the layout of the
result slots around it.

Layout of the result layers in world coordinates (the image's units), so that nothing
hides anything else and nothing shares the data's axes::

    row -1 [ diagnosis maps           ] [                   ] [ mean residuals ]
    row 0  [ image                    ] [ PSF grid          ] [ PSF basis h_i ]
    row 1  [ patch gallery (Review)   ] [ coefficient maps  ] [ PSF at (y, x) ]
    row 2  [ family's spatial basis   ] [ family's PSF grid ] [ family's h_i  ] [ conditions ]

The gap between slots leaves room for a title above each slot and a colour bar with its
labels to the right of it (:mod:`.figure`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .names import STEP_KEY

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

# ------------------------------------------------------------------ results
#: Gap between two rows of slots, as a fraction of the image's larger side: room for a
#: title of two lines above each slot at the zoom that shows the whole layout.
ROW_GAP = 0.18
#: Gap between two columns of slots: room for a colour bar and its labels right of a
#: map at that zoom.
COLUMN_GAP = 0.25


def slot_gap(frame: Frame, fraction: float = ROW_GAP) -> float:
    """World distance between two slots of the layout (rows; columns with COLUMN_GAP)."""
    return fraction * max(frame.height, frame.width)


def beside(frame: Frame, column: float, row: float = 0.0) -> tuple[float, float]:
    """World position of the top-left corner of the slot (``row``, ``column``); the
    image is slot (0, 0)."""
    return (frame.translate[0] + row * (frame.height + slot_gap(frame)),
            frame.translate[1] + column * (frame.width + slot_gap(frame, COLUMN_GAP)))


def below_others(viewer, frame: Frame, row: float, step: str, *,
                 results_only: bool = False) -> Frame:
    """``frame`` moved down so that its result row ``row`` starts below every layer of
    the viewer outside ``step``'s group (and sub-groups): results laid out from another
    image's frame (a family learnt from a stack beside a model learnt from one image)
    never land on the other results. With ``results_only``, only the other steps'
    results count, not the data: the frame moves only when they are in the way."""
    bottom = -np.inf
    for layer in viewer.layers:
        group = (layer.metadata or {}).get(STEP_KEY)
        if str(group).split("/")[0] == step or (results_only and group is None):
            continue
        bottom = max(bottom, float(np.asarray(layer.extent.world)[1][-2]))
    top = beside(frame, 0.0, row)[0]
    shift = max(0.0, bottom + slot_gap(frame) - top) if np.isfinite(bottom) else 0.0
    return Frame(frame.shape, frame.scale, (frame.translate[0] + shift, frame.translate[1]),
                 frame.index)



def free_slot(viewer, frame: Frame, step: str, *, row: float = 0.0,
              start: float = -1.0, step_by: float = -1.0, tries: int = 8
              ) -> tuple[float, float]:
    """The top-left corner of the first slot, from column ``start`` on by ``step_by``,
    that no other step's result covers (the data do not count: a result goes beside
    them). Beyond ``tries`` columns, the last one tried."""
    others = [np.asarray(layer.extent.world)[:, -2:] for layer in viewer.layers
              if (layer.metadata or {}).get(STEP_KEY) is not None
              and str(layer.metadata[STEP_KEY]).split("/")[0] != step]
    column = start
    for _ in range(tries):
        y0, x0 = beside(frame, column, row)
        lo = np.array([y0, x0])
        hi = lo + [frame.height, frame.width + slot_gap(frame, COLUMN_GAP)]
        if not any(np.all(np.minimum(hi, b[1]) > np.maximum(lo, b[0])) for b in others):
            return y0, x0
        column += step_by
    return y0, x0
