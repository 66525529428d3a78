"""Bookkeeping of the plugin's layers: found again by the name they were made as, grouped
by the step that made them, replaced together on a re-run and removed together."""

from __future__ import annotations

import contextlib

import numpy as np

from .figure import OVERLAYS_KEY, dress
from .frame import LayerTuple
from .names import MADE_AS, OPERATOR_KEY, STEP_KEY, SUBSPACE_KEY


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



#: Metadata keys that mark a layer as a result, not an image to work on: the plugin's
#: layers (:data:`MADE_AS`), a model's read back (its operator or family), a map's
#: description, a map shown with its colour bar.
RESULT_KEYS = (MADE_AS, OPERATOR_KEY, SUBSPACE_KEY, "about", OVERLAYS_KEY)


def is_input_image(layer, ndim: int | None = None) -> bool:
    """Whether ``layer`` is an image a step may work on: a greyscale image layer (of
    ``ndim`` dimensions, when given) that is no result (:data:`RESULT_KEYS`): not a
    gallery, a map or a mosaic."""
    if _kind(layer) != "image" or getattr(layer, "rgb", False):
        return False
    if ndim is not None and layer.ndim != ndim:
        return False
    return not any(key in (layer.metadata or {}) for key in RESULT_KEYS)


def input_images(viewer, ndim: int | None = None) -> list:
    """The viewer's images a step may work on (:func:`is_input_image`)."""
    return [layer for layer in viewer.layers if is_input_image(layer, ndim)]


def step_layers(viewer, step: str) -> list:
    """The layers the plugin made for ``step`` (its group)."""
    return [layer for layer in viewer.layers if (layer.metadata or {}).get(STEP_KEY) == step]


def group_layers(viewer, step: str) -> list:
    """The layers of ``step``'s group and of its sub-groups (``step + "/..."``: the 3D
    step's deblurred stack, kept when the step re-learns)."""
    return [layer for layer in viewer.layers
            if str((layer.metadata or {}).get(STEP_KEY, "")).split("/")[0] == step]


def remove_layers(viewer, layers) -> None:
    """Remove ``layers`` in one batch of the layer list: napari's canvas then cleans its
    scene graph (a full garbage collection) once for the batch, not once per layer, which
    took a quarter of a second a layer in a viewer holding a few dozen."""
    batch = getattr(viewer.layers, "batched_update", None)
    with batch() if batch is not None else contextlib.nullcontext():
        for layer in layers:
            viewer.layers.remove(layer)


def remove_step(viewer, step: str) -> int:
    """Remove the layers of one step's group and sub-groups; how many went."""
    gone = group_layers(viewer, step)
    remove_layers(viewer, gone)
    return len(gone)


def show_layers(viewer, tuples: list[LayerTuple], *, step: str | None = None,
                replace: bool = False) -> list:
    """Add the layers to the viewer, or update in place those the plugin made under the
    same name (whatever napari renamed them to).

    ``step`` tags the layers as that step's group; with ``replace``, the group's layers
    this call does not make again are removed (a re-run leaves the same layer set, never
    a stale title or map of the run before)."""
    out = []
    names = set()
    for data, kwargs, kind in tuples:
        name = kwargs["name"]
        names.add(name)
        meta = {**(kwargs.get("metadata") or {}), MADE_AS: name}
        if step is not None:
            meta[STEP_KEY] = step
        kwargs = kwargs | {"metadata": meta}
        layer = find_layer(viewer, name, kind)
        if layer is not None:
            if np.ndim(layer.data) != np.ndim(data) and kind == "image":
                viewer.layers.remove(layer)
                layer = None
            else:
                _update(layer, data, {k: v for k, v in kwargs.items() if k != "name"})
        if layer is None:
            layer = getattr(viewer, f"add_{kind}")(data, **kwargs)
        dress(layer)
        out.append(layer)
    if step is not None and replace:
        remove_layers(viewer, [layer for layer in step_layers(viewer, step)
                               if (layer.metadata or {}).get(MADE_AS) not in names])
    return out

def _update(layer, data, kwargs: dict) -> None:
    if "metadata" in kwargs:  # before the data: listeners of data events read it
        layer.metadata = kwargs["metadata"]
    if "features" in kwargs:  # points: data and features must change together
        layer.data = data
        layer.features = kwargs["features"]
    else:
        layer.data = data
    for key in ("scale", "translate", "units", "metadata", "contrast_limits"):
        if key in kwargs:
            setattr(layer, key, kwargs[key])
    if "contrast_limits" not in kwargs and hasattr(layer, "reset_contrast_limits"):
        layer.reset_contrast_limits()
    if hasattr(layer, "refresh_colors"):
        layer.refresh_colors()


def focus_on_step(viewer, step: str, *inputs, margin: float = 0.15) -> None:
    """Fit the view to one step's results: its group's layers (sub-groups included) and
    its input layers, in the plane shown. Only the camera moves. ``margin``: fraction
    of the canvas left around."""
    names = {layer.name for layer in inputs if layer is not None}
    layers = [layer for layer in viewer.layers if layer.name in names]
    layers += group_layers(viewer, step.split("/")[0])
    if not layers or viewer.dims.ndisplay != 2:
        return
    # the extents' last two axes (the plane shown), computed here: napari's
    # reset_view(layers=) fails on 2-D layers in a viewer holding a stack
    boxes = np.array([np.asarray(layer.extent.world, float)[:, -2:] for layer in layers])
    lo, hi = boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)
    size = np.maximum(hi - lo, 1e-12)
    # napari 0.9 keeps the camera in the scene and the canvas size in the model; before,
    # the viewer held the camera and the canvas size was the Qt canvas's (not sought:
    # the view then stays as it is)
    canvas = getattr(getattr(viewer, "canvas", None), "size", None)
    if canvas is None:
        return
    scene = getattr(viewer, "scene", None)
    camera = scene.camera if scene is not None else viewer.camera
    height, width = (float(v) for v in canvas)
    camera.center = tuple((lo + hi) / 2)
    camera.zoom = float((1 - margin) * min(height / size[0], width / size[1]))
