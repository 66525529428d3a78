"""Dock widget 6: deblur an image of point sources with a model or a family of operators.

With a family (a family file, or the *Learn family* result in the viewer), the
image's operator is first identified from its beads (a Points layer, or detected); with a
single model it is used as it is. The work (:func:`~napari_psfspace.core.restore.
identify_operator` then :func:`~napari_psfspace.core.restore.iter_deblur`) runs in a
worker thread with progress and *Cancel*; the sparse and smooth parts come back as
layers with the image's scale.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    FloatSpinBox,
    PushButton,
    SpinBox,
)
from napari.layers import Points
from napari.utils.notifications import show_error

from .._layers import (
    MADE_AS,
    OPERATOR_KEY,
    OVERLAYS_KEY,
    PSF_GRID,
    SUB_GRID,
    SUBSPACE_KEY,
    Frame,
    LayerTuple,
    advice_layers,
    field_units,
    image_plane,
    map_tuple,
    on_field,
    show_layers,
)
from ..core.common.device import array_module
from ..core.common.progress import Progress
from ..core.restore import identify_operator, iter_deblur
from ..core.restore.identify import IdentificationWarning
from ._view import show_step
from ._worker import CoreTask, device_choice, image_choices, result_text

if TYPE_CHECKING:
    import napari

#: Names of the result layers, before the slice and the unit.
SPARSE = "sparse part"
SMOOTH = "smooth part"
SPARSE_POINTS = "sparse points"
#: The sparse part's points shown at most (the brightest), and their size: the largest a
#: fraction of the field's side, the others by the square root of their amplitude, none
#: under :data:`SMALLEST_POINT` of it. A single pixel of a 1024 px field is otherwise
#: lost in a cell of the side-by-side view, a few hundred screen pixels wide.
MOST_POINTS = 5000
POINT_SIZE = 0.025
SMALLEST_POINT = 0.4
SOURCES = ("file (family or model)", "from the viewer")


def _identify_and_deblur(plane, model, beads, **kwargs):
    """Identify the operator when ``model`` is a family, then deblur (in the worker)."""
    from ..core.family import OperatorFamily

    op, note = model, "the model as it is"
    if isinstance(model, OperatorFamily):
        yield Progress("identify", 0.0, "identifying the operator from the beads")
        with warnings.catch_warnings():  # shown in the note instead
            warnings.simplefilter("ignore", IdentificationWarning)
            op = identify_operator(plane, model, beads=beads)
        note = identification_note(op.metadata["identification"])
    res = yield from iter_deblur(plane, op, **kwargs)
    return res, op, note


def identification_note(info: dict) -> str:
    """One paragraph on an identification: its beads, its error band, its warning."""
    left = info.get("left_out") or []
    band = info.get("error_band")
    return (f"identified from {info['n_beads']} beads"
            + (f" ({len(left)} clicked left out: they disagree with the others)"
               if left else "")
            + ("" if band is None
               else f"; its PSFs are off by {100 * band[0]:.0f}-{100 * band[1]:.0f} % "
                    "over the field (90 % range)")
            + (f". WARNING: {info['warning']}" if info.get("warning") else "")
            + ("" if info.get("more_beads_at") is None
               else ". The yellow cross (layer \"one more bead here\"): where one more "
                    "bead would help most"))


def _limits(values: np.ndarray) -> tuple[float, float]:
    """Contrast limits that show a sparse image's single points: 0 to the 99.9th
    percentile of its nonzero values (not of every pixel, which is 0 for most)."""
    nz = np.abs(values[np.isfinite(values) & (values != 0)])
    top = float(np.percentile(nz, 99.9)) if nz.size else 1.0
    lo = float(min(np.nanmin(values), 0.0)) if values.size else 0.0
    return lo, max(top, lo + 1e-12)


def display_limits(plane: np.ndarray) -> tuple[float, float]:
    """Contrast limits of an image from its values: the 0.5th to the 99.9th percentile
    of its finite pixels (a bead image's few bright pixels would set the full range, and
    its background would read black)."""
    values = np.asarray(plane, np.float64)
    values = values[np.isfinite(values)]
    if not values.size:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(values, [0.5, 99.9]))
    return lo, max(hi, lo + 1e-12)


def result_layers(res, frame: Frame, layer, *,
                  limits: tuple[float, float] | None = None) -> list[LayerTuple]:
    """The sparse part, its points and the smooth part, on the image's field, in the
    image's units: the smooth part at ``limits`` (the input's contrast, the same side by
    side; by default the input layer's own), the sparse part from its values
    (:func:`_limits`). From a stack's slice the parts are one-plane stacks on that slice
    (shown with it, not over every slice), named for it."""
    where = "" if frame.index is None else f", slice {frame.index}"
    meta = {"pixel_size_um": frame.pixel_size, "deblur": res.parameters,
            "source": layer.name, "slice": frame.index}
    place = on_field(frame, np.shape(res.sparse))
    shown = limits if limits is not None else getattr(layer, "contrast_limits", None)
    out: list[LayerTuple] = []
    for part, name, cmap in ((res.sparse, SPARSE, "magma"), (res.smooth, SMOOTH, "gray")):
        part = np.asarray(part, np.float32)
        limits = (tuple(float(v) for v in shown) if name == SMOOTH and shown is not None
                  else _limits(part))
        kwargs = {"name": f"{name}{where} (image units)", **place, "colormap": cmap,
                  "contrast_limits": limits, "metadata": meta}
        out.append(map_tuple(part, kwargs, "", frame))
    out.append(sparse_points(res.sparse, frame, out[0][1], f"{SPARSE_POINTS}{where} "
                             "(image units)", meta))
    if frame.index is not None:  # on the slice it came from
        dz, tz = float(layer.scale[0]), float(layer.translate[0])
        z = tz + frame.index * dz
        for i, (data, kwargs, kind) in enumerate(out):
            if "units" in kwargs:  # one more axis: z, in the stack's unit
                kwargs = kwargs | {"units": (kwargs["units"][0],) * 3}
            if kind == "image" and np.ndim(data) == 2:
                out[i] = (data[None], kwargs | {"scale": (dz, *kwargs["scale"]),
                                                "translate": (z, *kwargs["translate"])},
                          kind)
            else:
                out[i] = (np.column_stack([np.full(len(data), z), data]), kwargs, kind)
    return out


def sparse_points(sparse: np.ndarray, frame: Frame, image_kwargs: dict, name: str,
                  meta: dict) -> LayerTuple:
    """The sparse part's nonzero pixels as points over its image layer (same place and
    scale), each sized and coloured by its amplitude: visible at the home view, where the
    image's single pixels are not.

    Parameters
    ----------
    sparse : ndarray of shape (M, N)
    frame : Frame
    image_kwargs : dict
        The sparse image layer's kwargs (its ``scale``, ``translate`` and
        ``contrast_limits``).
    name, meta : the layer's name and metadata.
    """
    values = np.asarray(sparse, np.float64)
    rows, cols = np.nonzero(np.isfinite(values) & (values > 0))
    amp = values[rows, cols]
    keep = np.argsort(amp)[::-1][:MOST_POINTS]
    rows, cols, amp = rows[keep], cols[keep], amp[keep]
    scale = np.asarray(image_kwargs["scale"], float)[-2:]
    origin = np.asarray(image_kwargs["translate"], float)[-2:]
    pos = origin + np.column_stack([rows, cols]) * scale
    top = float(image_kwargs["contrast_limits"][1]) or 1.0
    side = POINT_SIZE * max(frame.height, frame.width)
    size = side * np.clip(np.sqrt(amp / top), SMALLEST_POINT, 1.0)
    colour = ({"face_color": "amplitude", "face_colormap": "magma",
               "face_contrast_limits": (0.0, top)} if len(amp) else {})
    return (pos, {"name": name, "size": size, "features": {"amplitude": amp}, **colour,
                  "border_width": 0, "border_color": "transparent", **field_units(frame),
                  "metadata": {**meta, OVERLAYS_KEY: {"unit": ""},
                               "about": "the sparse part's nonzero pixels, sized and "
                                        "coloured by their amplitude (image units)"}},
            "points")


def _viewer_models(viewer) -> list:
    """(label, layer name) of the layers holding an operator or a family: the model is
    looked up by name when the deblur starts, so a step re-run in place (the same
    layer, a new model) is the one used."""
    out = []
    for layer in viewer.layers:
        meta = getattr(layer, "metadata", None) or {}
        made = meta.get(MADE_AS)
        if SUBSPACE_KEY in meta:
            out.append(("Family step's family" if made == SUB_GRID
                        else f"family: {layer.name}", layer.name))
        elif OPERATOR_KEY in meta:
            label = "Model step's model" if made == PSF_GRID else f"model: {layer.name}"
            out.append((meta.get("model_label", label), layer.name))
    return out


def _model_of(viewer, name: str):
    """The operator or family held by the layer ``name`` (None if it holds none now)."""
    if name not in viewer.layers:
        return None
    meta = viewer.layers[name].metadata or {}
    return meta.get(SUBSPACE_KEY, meta.get(OPERATOR_KEY))


class DeblurWidget(Container):
    """Sparse + smooth deblurring with a model, or blind with a family (BSS)."""

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self._viewer = viewer
        self.image = ComboBox(label="image", choices=image_choices(viewer))
        self.source = ComboBox(label="operator", choices=list(SOURCES))
        self.path = FileEdit(mode="r", filter="*.npz", label="file")
        self.in_viewer = ComboBox(label="in the viewer", choices=self._models, visible=False)
        self.points = ComboBox(label="beads", choices=self._points)
        self.points.tooltip = ("Beads to identify a family's operator from (5 or more; "
                               "10 spread over the field identify it better than 5); "
                               "(detect) finds them. Ignored for a model.")
        self.auto = CheckBox(value=True, text="weights from the noise")
        self.sparse_weight = FloatSpinBox(label="sparse weight", min=0.0, max=1e12,
                                          value=1.0, visible=False)
        self.smooth_weight = FloatSpinBox(label="smooth weight", min=0.0, max=1e12,
                                          value=1e3, visible=False)
        self.max_iter = SpinBox(label="iterations at most", min=1, max=100000, value=500)
        self.refit = CheckBox(value=False, text="refit the points' flux")
        self.refit.tooltip = ("After the deblurring, one least-squares scale per cluster of "
                              "points: their flux without the l1 shrinkage (spurious "
                              "points rise too)")
        self.device = device_choice()
        self.run_button = PushButton(text="Deblur")
        self.task = CoreTask(self.run_button)
        self.result = result_text()
        super().__init__(widgets=[
            self.image, self.source, self.path, self.in_viewer, self.points, self.auto,
            self.sparse_weight, self.smooth_weight, self.max_iter, self.refit, self.device,
            self.run_button,
            self.task, self.result])
        self.source.changed.connect(self._on_source)
        self.auto.changed.connect(self._on_auto)
        self.run_button.changed.connect(self.run)
        viewer.layers.events.inserted.connect(self._on_layers)
        viewer.layers.events.removed.connect(lambda *_: self.reset_choices())
        self.last = None  # the last Deblurred
        self.operator = None  # and the operator it used (identified or given)

    def _models(self, _widget=None) -> list:
        return _viewer_models(self._viewer)

    def _points(self, _widget=None) -> list:
        pts = [(p.name, p) for p in self._viewer.layers if isinstance(p, Points)]
        return [("(detect)", None), *pts]

    def _on_source(self, *_) -> None:
        file = self.source.value == SOURCES[0]
        self.path.visible = file
        self.in_viewer.visible = not file

    def _on_layers(self, *_) -> None:
        """New layers: refresh the choices; a model or family just learnt in the viewer
        becomes the operator, unless the user chose a file."""
        self.reset_choices()
        models = self._models()
        if models and str(self.path.value) in ("", "."):
            self.source.value = SOURCES[1]
            self.in_viewer.value = models[-1][1]

    def _on_auto(self, *_) -> None:
        for w in (self.sparse_weight, self.smooth_weight):
            w.visible = not self.auto.value

    def model(self):
        """The chosen operator or family; raises ValueError naming the field."""
        if self.source.value == SOURCES[1]:
            name = self.in_viewer.value
            model = None if name is None else _model_of(self._viewer, name)
            if model is None:
                raise ValueError("in the viewer: no model or family yet (learn one with "
                                 "Learn operator or Learn family, or open a file)")
            return model
        path = str(self.path.value)
        if path in ("", "."):
            raise ValueError("file: choose a model or family file (.npz)")
        from ..core.family.family_file import FORMAT_NAME
        from ..core.family.result import load_family
        from ..core.model.operator import load_operator
        from ..core.model.operator_file import archive_format

        p = Path(path)
        return load_family(p) if archive_format(p) == FORMAT_NAME else load_operator(p)

    def run(self, *_) -> None:
        """Deblur in a worker thread; add the sparse and smooth parts when done."""
        layer = self.image.value
        try:
            if layer is None:
                raise ValueError("image: open an image first")
            plane, frame = image_plane(layer, self._viewer.dims.point)
            model = self.model()
            device = array_module(str(self.device.value))  # a missing GPU: one line
            beads = None
            pts = self.points.value
            if pts is not None and len(pts.data):
                beads = np.asarray(pts.data, float)[:, -2:]
                beads = (beads - np.asarray(frame.translate)) / np.asarray(frame.scale)
        except (ValueError, OSError) as exc:
            show_error(str(exc))
            self.task.status.value = str(exc)
            return
        weights = {} if self.auto.value else {
            "sparse_weight": float(self.sparse_weight.value),
            "smooth_weight": float(self.smooth_weight.value)}
        gen = _identify_and_deblur(plane, model, beads, max_iter=int(self.max_iter.value),
                                   debias=bool(self.refit.value), device=device, **weights)

        def on_result(got) -> None:
            res, op, note = got
            self.last, self.operator = res, op
            # the input and the smooth part at one contrast, from the input's values
            limits = display_limits(plane)
            layer.contrast_limits = limits
            tuples = result_layers(res, frame, layer, limits=limits)
            info = (op.metadata or {}).get("identification")
            if info:  # on the input: where one more bead would help, beads left out
                tuples += advice_layers(info, frame, (float(layer.scale[0]),
                                                      float(layer.translate[0])))
            shown = show_layers(self._viewer, tuples, step="Deblur", replace=True)
            for made in shown:  # nothing selected: napari draws selected points boxed
                if hasattr(made, "selected_data"):
                    made.selected_data = set()
            self._viewer.layers.selection.active = shown[1]  # the smooth part
            show_step(self, "Deblur", layer)
            p = res.parameters
            self.result.value = (
                f"{note}; {res.iterations} iterations "
                f"({'converged' if res.converged else 'stopped at the limit'}) on the "
                f"{p['device'].upper()}, {p['seconds']:.1f} s\nsparse weight "
                f"{p['sparse_weight']:.3g}, smooth weight {p['smooth_weight']:.3g} "
                f"(noise sd {p['noise_sd']:.3g})")

        self.task.run(gen, on_result)
