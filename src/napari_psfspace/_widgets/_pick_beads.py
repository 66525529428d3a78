"""Dock widget 1: detect beads into a Points layer the user can edit."""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import ComboBox, Container, FloatSpinBox, Label, PushButton

from .._layers import (
    BEADS,
    HOT_PIXELS,
    STATUS_COLORS,
    STATUS_MEANING,
    beads_layer,
    find_layer,
    fix_ids,
    hot_pixels_layer,
    image_plane,
    show_layers,
)
from ..core.beads.steps import (
    iter_detect_beads,
    iter_suggest_psf_radius,
    iter_suggest_slice_radius,
)
from ._worker import CoreTask, RadiusEdit, image_choices, pixel_size_of

if TYPE_CHECKING:
    import napari

DEFAULT_RADIUS_PX = 10.0
_WATCHED: weakref.WeakSet = weakref.WeakSet()  # Points layers whose ids we maintain


def legend_html() -> str:
    """Coloured status legend for a Label."""
    return "<br>".join(f'<span style="color:{STATUS_COLORS[s]}">&#9711;</span> '
                       f"{STATUS_MEANING[s]}" for s in STATUS_COLORS)


def watch_points(layer) -> None:
    """Give points added by hand status "kept" (feature default) and a new unique id."""
    if layer in _WATCHED:
        return

    def on_data(event=None) -> None:
        if getattr(event, "action", "added") not in ("added", None):
            return
        feats = layer.features
        if "id" in feats and len(feats):
            ids = fix_ids(feats["id"])
            if (ids != feats["id"].to_numpy()).any():
                feats["id"] = ids
                layer.features = feats

    layer.events.data.connect(on_data)
    _WATCHED.add(layer)


class PickBeadsWidget(Container):
    """Detect beads in an image layer; the result is a Points layer named "beads" (and,
    when the image has some, a "hot pixels" layer of the pixels masked as narrower than
    the optics can form).

    Each point has the features ``id``, ``amplitude`` and ``status`` (its colour). Add,
    delete or move points with napari's Points tools: the other widgets read the layer.
    """

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self._viewer = viewer
        self.image = ComboBox(label="image", choices=image_choices(viewer))
        self.radius = RadiusEdit()
        self.suggest = PushButton(text="Suggest radius")
        self.suggest.tooltip = ("Measure the enclosed energy of bright spots across the "
                                "field and propose a radius that bounds the widest PSFs.")
        self.threshold = FloatSpinBox(value=8.0, min=0.5, max=1000.0, step=0.5,
                                      label="threshold")
        self.threshold.tooltip = ("Detection threshold in noise standard deviations of the "
                                  "filtered image: lower finds fainter beads.")
        self.bead_diameter = FloatSpinBox(value=0.0, min=0.0, max=5000.0, step=10.0,
                                          label="bead diameter (nm)")
        self.bead_diameter.tooltip = (
            "The beads' diameter from their data sheet (0: point sources). The learnt PSFs "
            "are corrected for it (the sphere is divided out). Needs the image's pixel "
            "size.")
        self.detect = PushButton(text="Detect beads")
        self.task = CoreTask(self.detect)
        self.legend = Label(value=legend_html())
        self.help = Label(value="Edit the points by hand: add (+), delete, move.\n"
                                "Rejected beads are not used to learn the PSF.")
        super().__init__(widgets=[self.image, self.radius, self.suggest, self.threshold,
                                  self.bead_diameter, self.detect, self.task, self.legend,
                                  self.help])
        from qtpy.QtWidgets import QSizePolicy

        for label in (self.legend, self.help):  # the dock's width, not the text's
            label.native.setWordWrap(True)
            label.native.setSizePolicy(QSizePolicy.Policy.Ignored,
                                       QSizePolicy.Policy.MinimumExpanding)
        self.image.changed.connect(self._on_image)
        self.detect.changed.connect(self.run)
        self.suggest.changed.connect(self.run_suggest)
        viewer.layers.events.inserted.connect(self.reset_choices)
        viewer.layers.events.removed.connect(self.reset_choices)
        self.reset_choices()
        self._on_image()

    def _on_image(self, *_) -> None:
        layer = self.image.value
        if layer is None:
            return
        meta = layer.metadata or {}
        self.radius.set_calibration(pixel_size_of(layer),
                                    meta.get("psf_radius", DEFAULT_RADIUS_PX))

    def _plane(self):
        """The plane on display of the chosen image, or None (the user is told why)."""
        layer = self.image.value
        if layer is None:
            self.task.status.value = "Open a bead image first (or File > Open Sample)."
            return None
        try:
            return image_plane(layer, self._viewer.dims.point)
        except ValueError as exc:
            from napari.utils.notifications import show_error

            show_error(str(exc))
            return None

    def run_suggest(self, *_) -> None:
        """Suggest the PSF radius from the chosen image (in a worker thread)."""
        if self.task.running:
            return
        got = self._plane()
        if got is None:
            return
        plane, frame = got
        if frame.index is not None:  # a stack's slice: from it and its neighbours
            def on_slice(found) -> None:
                self.radius.set_calibration(self.radius.pixel_size, found.radius)
                self.task.status.value = (f"suggested PSF radius: {found.radius:g} px"
                                          + (f". {found.reason}" if found.reason else ""))

            self.task.run(iter_suggest_slice_radius(self.image.value.data, frame.index),
                          on_slice)
            return

        def on_result(radius: float) -> None:
            self.radius.set_calibration(self.radius.pixel_size, radius)
            self.task.status.value = f"suggested PSF radius: {radius:g} px"

        self.task.run(iter_suggest_psf_radius(plane), on_result)

    def run(self, *_) -> None:
        """Detect beads in the chosen image (in a worker thread)."""
        layer = self.image.value
        got = self._plane()
        if got is None:
            return
        plane, frame = got
        r = self.radius.pixels
        diameter_nm = float(self.bead_diameter.value)
        px = self.radius.pixel_size
        if diameter_nm > 0 and not px:
            from napari.utils.notifications import show_error

            show_error("The bead diameter needs the image's pixel size, which this image "
                       "does not give: set the layer's scale (µm per pixel), or leave the "
                       "diameter at 0 (point sources).")
            return
        diameter_px = diameter_nm / 1000.0 / px if diameter_nm > 0 else 0.0

        def on_result(beads) -> None:
            data, kwargs, kind = beads_layer(beads, frame, r)
            kwargs["metadata"] = {**kwargs.get("metadata", {}), "psf_radius_px": r,
                                  "image": layer.name, "slice": frame.index,
                                  "threshold": float(self.threshold.value),
                                  "bead_diameter_nm": diameter_nm,
                                  "bead_diameter_px": diameter_px}
            tuples = [(data, kwargs, kind)]
            hot = np.zeros((0, 2)) if beads.hot_pixels is None else beads.hot_pixels
            stale = find_layer(self._viewer, HOT_PIXELS, "points") is not None
            if len(hot) or stale:  # never leave a stale one
                tuples.insert(0, hot_pixels_layer(hot, frame))
            points = show_layers(self._viewer, tuples, step="Beads", replace=True)[-1]
            watch_points(points)
            self._viewer.layers.selection.active = points
            self.task.status.value = beads.summary()

        self.task.run(iter_detect_beads(plane, r, threshold=float(self.threshold.value)),
                      on_result)


__all__ = ["BEADS", "PickBeadsWidget"]
