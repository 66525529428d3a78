"""The side-by-side view: a step's result maps beside its input, through napari's grid.

Every result lies on its image's field (``_layers.frame.on_field``), so napari's grid
(one layer a cell, one camera) shows each map beside the image at the same place of the
field: zoom and pan act on all of them. In each cell napari draws the layer's name
(top left) and colour bar (bottom right) (``_layers.figure``); the camera leaves them
room beside the data at the view this module sets. The scale bar reads the layers'
units.

The view shows the step's input and the step's maps; it hides the other layers while it
is on and gives back, when it is left, the user's grid settings and every visibility it
changed. Steps whose results are clicked on the image (Beads, Review) leave it.
"""

from __future__ import annotations

import numpy as np

from .._layers import OVERLAYS_KEY, focus_on_step, group_layers
from .._layers.figure import BAR_FONT, BAR_SIZE, NAME_FONT, bar_of

#: Steps shown side by side (their results are maps to read, not marks to click).
SIDE_BY_SIDE_STEPS = ("Model", "Diagnose", "Family", "Deblur", "3D")
#: Screen pixels between two cells of the grid.
SPACING = 6
#: The scale bar's corner of the canvas: the bottom-left cell's, where no name or colour
#: bar is (names top left, colour bars bottom right).
SCALE_BAR_CORNER = "bottom_left"
#: Screen pixels a point of text takes at napari's 96 dpi, and the width of a
#: character in fractions of its font size: an upper estimate for napari's canvas font
#: (DejaVu Sans) over names and numbers.
POINT = 96 / 72
CHAR_WIDTH = 0.68
#: Screen pixels between a cell's edge and napari's overlays in it.
OVERLAY_PAD = 8
#: Screen pixels the scale bar takes (its bar and its text above it) in its corner.
SCALE_BAR_BOX = (40, 140)
#: Screen pixels left free in each cell, beside the data: above it for the layer's
#: name (a line of text in its box), right of it for the colour bar with its ticks and
#: their labels (up to six characters), below it for the scale bar, and a little on the
#: left.
MARGIN_TOP = int(np.ceil(NAME_FONT * POINT * 1.6)) + OVERLAY_PAD
MARGIN_RIGHT = int(np.ceil(BAR_SIZE[0] + 5 + 6 * CHAR_WIDTH * BAR_FONT * POINT)) + 16
MARGIN_BOTTOM = SCALE_BAR_BOX[0] + OVERLAY_PAD
MARGIN_LEFT = 4


def text_width(text: str, font_size: float) -> float:
    """Screen pixels a line of text takes at ``font_size`` points (an upper estimate)."""
    return len(text) * CHAR_WIDTH * font_size * POINT


def layout(canvas: tuple[float, float], n: int, extent: tuple[float, float],
           spacing: float = SPACING, min_width: float = 0.0) -> dict:
    """The grid and camera that show ``n`` cells of data of world ``extent`` (height,
    width) on a canvas of ``canvas`` (height, width) screen pixels, as large as they can
    be with each cell's margins free (:data:`MARGIN_TOP` and the others), in cells at
    least ``min_width`` pixels wide (the longest name) where any grid has them.

    Returns
    -------
    dict
        ``shape`` (rows, columns) of the grid, ``cell`` (height, width) in pixels,
        ``zoom`` (pixels per world unit) and ``offset`` (y, x): world distance from the
        data's centre to the camera's centre, which napari puts at each cell's centre
        (the data sit centred between the margins).
    """
    height, width = canvas
    best = None
    for cols in range(1, max(n, 1) + 1):
        rows = int(np.ceil(n / cols))
        cell = ((height - (rows - 1) * spacing) / rows, (width - (cols - 1) * spacing) / cols)
        free = (cell[0] - MARGIN_TOP - MARGIN_BOTTOM, cell[1] - MARGIN_LEFT - MARGIN_RIGHT)
        zoom = max(min(free[0] / extent[0], free[1] / extent[1]), 1e-9)
        named = cell[1] >= min_width
        better = best is None or (named, zoom) > (best["named"], best["zoom"] * (1 + 1e-9))
        if better:
            shift = ((MARGIN_BOTTOM - MARGIN_TOP) / 2, (MARGIN_RIGHT - MARGIN_LEFT) / 2)
            best = {"shape": (rows, cols), "cell": cell, "zoom": zoom, "named": named,
                    "offset": (shift[0] / zoom, shift[1] / zoom)}
    return best


def grid_of(viewer):
    """napari's grid model: ``viewer.canvas.grid`` (napari 0.9), else ``viewer.grid``."""
    grid = getattr(getattr(viewer, "canvas", None), "grid", None)
    return grid if grid is not None else viewer.grid


def scale_bar_of(viewer):
    """napari's scale bar: ``viewer.canvas.overlays.scale_bar`` (0.9), else
    ``viewer.scale_bar``."""
    overlays = getattr(getattr(viewer, "canvas", None), "overlays", None)
    bar = getattr(overlays, "scale_bar", None)
    return bar if bar is not None else viewer.scale_bar


class SideBySide:
    """The panel's side-by-side view of the step on show.

    Parameters
    ----------
    viewer : napari.Viewer
    on : bool
        Whether steps are shown side by side when they show results.
    """

    def __init__(self, viewer, on: bool = True) -> None:
        self.viewer = viewer
        self.on = on
        self.step: str | None = None
        self._inputs: dict[str, list[str]] = {}
        self._grid: dict | None = None  # the user's grid settings, while the view is on
        self._bar: dict | None = None  # the user's scale-bar settings
        self._hidden: set[str] = set()  # names of the layers the view hid
        self._named: set[str] = set()  # inputs whose name the view shows
        self._fitting = False
        # outside the grid, maps lie on each other: only the selected one is named and
        # barred, or their names and bars would pile up over the data
        viewer.layers.selection.events.active.connect(self.dress_maps)
        grid_of(viewer).events.enabled.connect(self.dress_maps)

    @property
    def active(self) -> bool:
        """Whether the view holds the user's grid settings (they are given back on
        :meth:`leave`)."""
        return self._grid is not None

    # ------------------------------------------------------------ entry points
    def show(self, step: str, *inputs) -> None:
        """A step showed its results: view them (side by side where it applies)."""
        self._inputs[step] = [layer.name for layer in inputs if layer is not None]
        self.show_tab(step)

    def show_tab(self, step: str) -> None:
        """The panel's page changed to ``step``. With the view on: the step's maps side
        by side with its input where it has maps (Model, Diagnose, Family, Deblur, 3D),
        else (Beads, Review) the user's grid and the image with the step's own layers,
        no other step's map over it. With the view off: the user's own view."""
        self.step = step
        if not self.on:
            self.leave()
            self._focus(step)
            return
        self._apply(step, grid=step in SIDE_BY_SIDE_STEPS and bool(self.maps(step)))

    def set_on(self, on: bool) -> None:
        """The panel's "side by side" box."""
        self.on = bool(on)
        if self.step is not None:
            self.show_tab(self.step)

    # ------------------------------------------------------------ the view
    def maps(self, step: str) -> list:
        """The step's layers shown in cells: those napari names (and bars)."""
        return [layer for layer in group_layers(self.viewer, step)
                if OVERLAYS_KEY in (layer.metadata or {})]

    def dress_maps(self, *_) -> None:
        """Each map's name and colour bar: on in napari's grid (a cell each), else only
        on the selected layer (maps on each other would pile their texts up)."""
        gridded = bool(grid_of(self.viewer).enabled)
        active = self.viewer.layers.selection.active
        chosen = None if active is None else active.name
        for layer in self.viewer.layers:
            meta = layer.metadata or {}
            if OVERLAYS_KEY not in meta:
                continue
            on = gridded or layer.name == chosen
            bar = bar_of(layer)
            if bar is not None:
                bar.visible = on
            if getattr(layer, "name_overlay", None) is not None:
                layer.name_overlay.visible = on

    def _focus(self, step: str) -> None:
        inputs = [self.viewer.layers[n] for n in self._inputs.get(step, [])
                  if n in self.viewer.layers]
        if step in self._inputs:
            focus_on_step(self.viewer, step, *inputs)

    def _apply(self, step: str, *, grid: bool) -> None:
        """Show ``step``: in napari's grid (``grid``), its inputs and maps and nothing
        else; else every layer but the other steps' maps (which would cover the image)."""
        g = grid_of(self.viewer)
        bar = scale_bar_of(self.viewer)
        if self._grid is None:
            self._grid = {"enabled": g.enabled, "stride": g.stride,
                          "shape": tuple(g.shape), "spacing": g.spacing}
            self._bar = {"visible": bool(bar.visible), "position": bar.position}
            # napari's Home button (reset_view) comes back to this view, not to one
            # whose data run under the names and colour bars
            self.viewer.events.reset_view.connect(self._on_home)
        if grid:
            names = [n for n in self._inputs.get(step, []) if n in self.viewer.layers]
            inputs = [self.viewer.layers[n] for n in names]
            shown = {layer.name for layer in [*inputs, *self.maps(step)]}
        else:
            ours = {layer.name for layer in self.maps(step)}
            shown = {layer.name for layer in self.viewer.layers
                     if OVERLAYS_KEY not in (layer.metadata or {}) or layer.name in ours}
            inputs = []
        self._name_inputs(inputs)
        for layer in self.viewer.layers:
            if layer.name in shown:
                if layer.name in self._hidden:
                    layer.visible = True
                    self._hidden.discard(layer.name)
            elif layer.visible:
                layer.visible = False
                self._hidden.add(layer.name)
        if grid:
            g.stride, g.shape, g.spacing = 1, (-1, -1), SPACING
            g.enabled = True
            bar.position = SCALE_BAR_CORNER
            bar.visible = True
            self.dress_maps()
            self.fit()
        else:
            self._give_back_grid()
            self.dress_maps()
            self._focus(step)

    def _name_inputs(self, inputs) -> None:
        """napari's name overlay on the inputs (and off on those named before)."""
        keep = {layer.name for layer in inputs}
        for name in self._named - keep:
            if name in self.viewer.layers:
                self.viewer.layers[name].name_overlay.visible = False
        self._named &= keep
        for layer in inputs:
            overlay = getattr(layer, "name_overlay", None)
            if overlay is not None and not overlay.visible:
                overlay.font_size, overlay.visible = NAME_FONT, True
                self._named.add(layer.name)

    def _give_back_grid(self) -> None:
        """The user's grid and scale-bar settings, as they were."""
        grid = grid_of(self.viewer)
        for key, value in (self._grid or {}).items():
            setattr(grid, key, value)
        bar = scale_bar_of(self.viewer)
        for key, value in (self._bar or {}).items():
            setattr(bar, key, value)

    def _on_home(self, *_) -> None:
        if not self._fitting:
            self.fit()

    def fit(self) -> None:
        """Set the grid's shape and the camera (:func:`layout`): each cell's data as
        large as they can be, the name and the colour bar beside them. Where napari keeps
        no canvas size in its model (before 0.9), napari's own view reset."""
        layers = [layer for layer in self.viewer.layers if layer.visible]
        size = getattr(getattr(self.viewer, "canvas", None), "size", None)
        if not layers or size is None or self.viewer.dims.ndisplay != 2:
            self._fitting = True
            try:
                self.viewer.reset_view()
            finally:
                self._fitting = False
            return
        boxes = np.array([np.asarray(layer.extent.world, float)[:, -2:] for layer in layers])
        lo, hi = boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)
        extent = np.maximum(hi - lo, 1e-12)
        longest = max(text_width(layer.name, NAME_FONT) for layer in layers)
        plan = layout(tuple(float(v) for v in size), len(layers),
                      (float(extent[0]), float(extent[1])), min_width=longest + 12)
        grid_of(self.viewer).shape = plan["shape"]
        scene = getattr(self.viewer, "scene", None)
        camera = scene.camera if scene is not None else self.viewer.camera
        camera.center = tuple((lo + hi) / 2 + np.asarray(plan["offset"]))
        camera.zoom = plan["zoom"]

    def leave(self) -> None:
        """Give back the user's grid, scale bar, and every visibility and input name the
        view changed."""
        if self._grid is None:
            return
        self.viewer.events.reset_view.disconnect(self._on_home)
        self._give_back_grid()
        for name in self._hidden:
            if name in self.viewer.layers:
                self.viewer.layers[name].visible = True
        self._name_inputs([])
        self._grid, self._bar, self._hidden = None, None, set()
        self.dress_maps()


def show_step(widget, step: str, *inputs) -> None:
    """A step widget showed its results: the panel's view shows them (``widget.side_view``,
    a :class:`SideBySide`, set by the panel), else the camera fits them."""
    view = getattr(widget, "side_view", None)
    if view is not None:
        view.show(step, *inputs)
    else:
        focus_on_step(widget._viewer, step, *inputs)


def _boxes_meet(a, b) -> bool:
    """Whether two screen boxes (y0, x0, y1, x1) overlap."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def collisions(viewer) -> list[str]:
    """What the grid view shows over what, read from napari's settings: for each cell,
    its data (its layer's extent through the camera), its name and its colour bar (the
    overlays' corners, font sizes and bar size, the name's length) and the scale bar.
    Texts are sized from their font (:func:`text_width`, an upper estimate). An empty
    list: no text over another or over the data, and every name within its cell.
    Empty also where napari keeps no canvas size in its model (before 0.9)."""
    size = getattr(getattr(viewer, "canvas", None), "size", None)
    grid = grid_of(viewer)
    if size is None or not grid.enabled:
        return []
    layers = list(viewer.layers)
    rows, cols = grid.actual_shape(layers)
    height, width = (float(v) for v in size)
    spacing = float(grid.spacing) if grid.spacing >= 1 else 0.0
    cell_h = (height - (rows - 1) * spacing) / rows
    cell_w = (width - (cols - 1) * spacing) / cols
    scene = getattr(viewer, "scene", None)
    camera = scene.camera if scene is not None else viewer.camera
    centre = np.asarray(camera.center, float)[-2:]
    zoom = float(camera.zoom)
    scale_bar_box = None
    found = []
    scale_bar = scale_bar_of(viewer)
    if scale_bar.visible:
        sh, sw = SCALE_BAR_BOX
        scale_bar_box = (height - OVERLAY_PAD - sh, OVERLAY_PAD, height - OVERLAY_PAD,
                         OVERLAY_PAD + sw)
    for index, layer in enumerate(layers):
        r, c = grid.position(index, layers)
        if r < 0 or not layer.visible:
            continue
        y0, x0 = r * (cell_h + spacing), c * (cell_w + spacing)
        extent = np.asarray(layer.extent.world, float)[:, -2:]
        mid = (y0 + cell_h / 2, x0 + cell_w / 2)
        lo = (extent[0] - centre) * zoom + mid
        hi = (extent[1] - centre) * zoom + mid
        data = (max(lo[0], y0), max(lo[1], x0), min(hi[0], y0 + cell_h), min(hi[1], x0 + cell_w))
        boxes = {"data": data}
        name = getattr(layer, "name_overlay", None)
        if name is not None and name.visible:
            w = text_width(layer.name, name.font_size)
            if w > cell_w - 2 * OVERLAY_PAD:
                found.append(f"{layer.name!r}: its name is wider than its cell")
            boxes["name"] = (y0 + OVERLAY_PAD - 4, x0 + OVERLAY_PAD,
                             y0 + OVERLAY_PAD + name.font_size * POINT * 1.6,
                             x0 + OVERLAY_PAD + w)
        bar = bar_of(layer)
        if bar is not None and bar.visible:
            bw = bar.size[0] + bar.tick_length + 6 * CHAR_WIDTH * bar.font_size * POINT
            bh = bar.size[1] + bar.font_size * POINT
            bar_box = (y0 + cell_h - OVERLAY_PAD - bh, x0 + cell_w - OVERLAY_PAD - bw,
                       y0 + cell_h - OVERLAY_PAD, x0 + cell_w - OVERLAY_PAD)
            boxes["colour bar"] = bar_box
        if scale_bar_box is not None and _boxes_meet(scale_bar_box, (y0, x0, y0 + cell_h,
                                                                    x0 + cell_w)):
            boxes["scale bar"] = scale_bar_box
        keys = list(boxes)
        for i, a in enumerate(keys):
            for b in keys[i + 1:]:
                if _boxes_meet(boxes[a], boxes[b]):
                    found.append(f"{layer.name!r}: its {a} and its {b} overlap")
    return found
