"""How a result map is read: napari draws its name and its colour bar on the canvas
(``layer.name_overlay``, ``layer.colorbar``; a Points layer's ``face_colorbar``), and the
scale bar from the layer's units. Nothing of a figure is drawn as data.

A map's layer-data tuple carries :data:`OVERLAYS_KEY` in its metadata; :func:`dress`
turns the overlays on once napari made the layer. Names and bars sit in the corners of
the layer's grid cell: :data:`NAME_CORNER` and :data:`BAR_CORNER`, at the font sizes
here, so that the view (``_widgets._view``) leaves them room beside the data.
"""

from __future__ import annotations

import numpy as np

from .frame import Frame, LayerTuple, field_units

#: Metadata key of a layer shown with its name and colour bar: ``{"unit": ...}``; a
#: unit of None: its name only (marks of one colour, no scale to read).
OVERLAYS_KEY = "psfspace_overlays"
#: Corners of the name and of the colour bar in each grid cell (napari's positions).
NAME_CORNER = "top_left"
BAR_CORNER = "bottom_right"
#: Font size of the name and of the bar's ticks, in screen pixels.
NAME_FONT = 8
BAR_FONT = 8
#: The colour bar's (width, height) in screen pixels.
BAR_SIZE = (12, 100)


def map_tuple(data: np.ndarray, kwargs: dict, unit: str, frame: Frame) -> LayerTuple:
    """A result map's image layer-data tuple: named by its quantity and unit, in the
    image's units, marked to be shown with its name and colour bar (:func:`dress`).

    Parameters
    ----------
    data : ndarray of shape (..., M, N)
    kwargs : dict
        The layer's kwargs: ``name`` (quantity and unit), ``scale``, ``translate``,
        ``colormap`` and ``contrast_limits`` are required.
    unit : str
        Unit of the values ("" for none or relative).
    frame : Frame
        The image's frame: the layer's axes get its unit.
    """
    meta = {**(kwargs.get("metadata") or {}), "unit": unit, OVERLAYS_KEY: {"unit": unit}}
    return (data, {**field_units(frame, np.ndim(data)), **kwargs, "metadata": meta}, "image")


def bar_of(layer):
    """The colour-bar overlay napari draws for a map layer (an image's ``colorbar``, a
    Points layer's ``face_colorbar``), or None: no such overlay, or a layer whose marks
    have no scale to read (:data:`OVERLAYS_KEY` with a unit of None)."""
    meta = (getattr(layer, "metadata", None) or {}).get(OVERLAYS_KEY) or {}
    if "unit" in meta and meta["unit"] is None:
        return None
    return getattr(layer, "colorbar", None) or getattr(layer, "face_colorbar", None)


def finite_limits(values) -> tuple[float, float]:
    """Colour limits spanning the finite values (0 to 1 where there are none), never
    empty (a constant map gets a range above its value)."""
    values = np.asarray(values, float)
    finite = values[np.isfinite(values)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    return (lo, hi) if hi > lo else (lo, lo + max(abs(lo), 1e-6))


def dress(layer) -> None:
    """Turn on napari's name and colour-bar overlays of a layer made by
    :func:`map_tuple` (or a Points layer whose metadata holds :data:`OVERLAYS_KEY`);
    other layers are left as they are. Read duck-typed: napari 0.7 and later."""
    if OVERLAYS_KEY not in (getattr(layer, "metadata", None) or {}):
        return
    bar = bar_of(layer)
    if bar is not None:
        bar.position = BAR_CORNER
        bar.size = BAR_SIZE
        bar.font_size = BAR_FONT
        bar.visible = True
    name = getattr(layer, "name_overlay", None)
    if name is not None:
        name.position = NAME_CORNER
        name.font_size = NAME_FONT
        name.visible = True
