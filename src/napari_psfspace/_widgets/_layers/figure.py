"""What makes the result slots read as one figure: a title above each slot, and beside
each map a colour bar whose texts give its limits in the map's unit.

Both are plain layers in world coordinates (an image ramp and a points layer of texts),
so each map has its own bar beside it, never a canvas overlay stacked over the data.
Texts are drawn at a fixed screen size: the slots' gaps (:mod:`.frame`) leave room for
them at the zoom that shows the whole layout.
"""

from __future__ import annotations

import numpy as np

from .frame import Frame, LayerTuple

#: Prefix of a colour bar's layers: "colour bar: <map name>" (the ramp) and
#: "colour bar text: <map name>" (its labels).
BAR = "colour bar: "
BAR_TEXT = "colour bar text: "
#: Levels of a colour bar's ramp.
BAR_LEVELS = 128


def titles_layer(name: str, entries: list[tuple[float, float, str]], frame: Frame
                 ) -> LayerTuple:
    """A points layer whose texts title the result slots: ``entries`` of (world row,
    world column, text), each text's lower-left corner just above that position (the
    slot's top-left corner), in the gap above the slot. Titles are short (two lines at
    most: the canvas shows three slots side by side); each layer's
    ``metadata["about"]`` says the rest."""
    pos = np.array([[y, x] for y, x, _ in entries], float).reshape(-1, 2)
    lift = 0.012 * max(frame.height, frame.width)
    return (pos - [lift, 0.0],
            {"name": name, "features": {"title": [t for _, _, t in entries]},
             "text": {"string": "{title}", "size": 8, "color": "white",
                      "anchor": "upper_left"},  # napari: the text above the point
             "size": 0.001 * max(frame.height, frame.width), "face_color": "transparent",
             "border_width": 0, "metadata": {"about": "titles of the result mosaics"}},
            "points")


def _tick(value: float, unit: str) -> str:
    """A limit as short as it reads: 3 significant digits, whole numbers up to 1e7
    written out (76300, not 7.63e+04)."""
    text = f"{value:.0f}" if 1e4 <= abs(value) < 1e7 else f"{value:.3g}"
    return f"{text} {unit}" if unit else text


def colorbar_layers(name: str, unit: str, colormap: str, limits: tuple[float, float],
                    slot: tuple[float, float, float, float], frame: Frame
                    ) -> list[LayerTuple]:
    """A vertical colour bar right of a map's slot, and its texts.

    Parameters
    ----------
    name : str
        The map layer's name (it names the quantity and unit); the bar's layers are
        ``"colour bar: " + name`` and ``"colour bar text: " + name``.
    unit : str
        Unit of the map's values, written after each limit ("" for none).
    colormap : str
    limits : (float, float)
        The map's contrast limits: the bar's bottom and top.
    slot : (float, float, float, float)
        World (top, left, height, width) of the map.
    frame : Frame
        The image's frame (sets the bar's width and its distance to the map).

    Returns
    -------
    list of (data, kwargs, layer_type)
        The ramp (an image of :data:`BAR_LEVELS` rows, top = ``limits[1]``) and a
        points layer of three texts: the top limit, the middle, the bottom limit.
    """
    top, left, height, width = (float(v) for v in slot)
    lo, hi = (float(v) for v in limits)
    size = max(frame.height, frame.width)
    pad, bar_w = 0.015 * size, 0.03 * size
    x_bar = left + width + pad
    ramp = np.linspace(hi, lo, BAR_LEVELS, dtype=np.float32)[:, None]
    about = {"colorbar_of": name, "unit": unit, "limits": [lo, hi]}
    step = height / BAR_LEVELS
    bar = (ramp, {"name": BAR + name, "scale": (step, bar_w),
                  "translate": (top + step / 2, x_bar + bar_w / 2),
                  "colormap": colormap, "contrast_limits": (lo, hi),
                  "metadata": {**about, "about": f"colour bar of {name!r}"}}, "image")
    x_text = x_bar + bar_w + pad
    pos = np.array([[top, x_text], [top + height / 2, x_text], [top + height, x_text]])
    texts = [_tick(hi, unit), _tick((lo + hi) / 2, unit), _tick(lo, unit)]
    labels = (pos, {"name": BAR_TEXT + name, "features": {"tick": texts},
                    "text": {"string": "{tick}", "size": 7, "color": "white",
                             "anchor": "lower_left"},  # napari: below each point
                    "size": 0.001 * size, "face_color": "transparent", "border_width": 0,
                    "metadata": {**about, "about": f"limits of {name!r}'s colour bar"}},
              "points")
    return [bar, labels]


def map_layers(data: np.ndarray, kwargs: dict, unit: str, frame: Frame) -> list[LayerTuple]:
    """A map's image layer-data tuple followed by its colour bar's
    (:func:`colorbar_layers`), placed right of the map's extent.

    Parameters
    ----------
    data : ndarray of shape (M, N)
    kwargs : dict
        The map's layer kwargs: ``name`` (quantity and unit), ``scale``, ``translate``,
        ``colormap`` and ``contrast_limits`` are required.
    unit : str
        Unit of the values ("" for none).
    frame : Frame
    """
    scale = np.asarray(kwargs["scale"], float)[-2:]
    origin = np.asarray(kwargs["translate"], float)[-2:]
    shape = np.shape(data)[-2:]
    top, left = origin - scale / 2
    slot = (top, left, shape[0] * scale[0], shape[1] * scale[1])
    meta = {**(kwargs.get("metadata") or {}), "unit": unit}
    return [(data, kwargs | {"metadata": meta}, "image"),
            *colorbar_layers(kwargs["name"], unit, kwargs["colormap"],
                             kwargs["contrast_limits"], slot, frame)]
