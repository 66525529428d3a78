"""Dock widget 2: review the bead patches, accept or reject beads."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import ComboBox, Container, PushButton, SpinBox

from .._layers import (
    CURRENT,
    GALLERY,
    STATUS_MEANING,
    beads_from_points,
    ensure_bead_features,
    field_units,
    find_layer,
    focus_on_step,
    gallery_cell,
    gallery_index,
    gallery_layers,
    set_statuses,
    show_layers,
)
from ..core.beads.detect import REJECTED
from ..core.model.review import VIEWS, PatchReview, iter_patch_review
from ._worker import (
    CoreTask,
    FollowsBeads,
    RadiusEdit,
    bead_layer_choices,
    image_choices,
    result_text,
)

if TYPE_CHECKING:
    import napari


class ReviewPatchesWidget(FollowsBeads, Container):
    """A gallery of bead patches (a 2-D mosaic right of the image) with their flags.

    The *patch* field, or a click on a patch of the gallery, picks the bead on display
    (outlined in the gallery, selected in the beads layer, described in the widget).
    Accept / Reject set the bead's status in the Points layer, which the operator
    learning reads. Views: raw, background removed, windowed. The gallery shares no
    axis with the data: a z-stack's slider stays where the user left it.
    """

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self._viewer = viewer
        self.image = ComboBox(label="image", choices=image_choices(viewer))
        self.points = ComboBox(label="beads", choices=bead_layer_choices(viewer))
        self.radius = RadiusEdit()
        self.extract = PushButton(text="Extract patches")
        self.task = CoreTask(self.extract)
        self.view = ComboBox(label="view", choices=list(VIEWS), value="background removed")
        self.patch = SpinBox(label="patch", min=0, max=0, enabled=False)
        self.info = result_text(3)
        self.accept = PushButton(text="Accept bead", enabled=False)
        self.reject = PushButton(text="Reject bead", enabled=False)
        super().__init__(widgets=[
            self.image, self.points, self.radius, self.extract, self.task, self.view,
            self.patch, self.info, Container(widgets=[self.accept, self.reject],
                                             layout="horizontal", labels=False)])
        self.review: PatchReview | None = None
        self._ids = np.zeros(0, np.int64)
        self._frame = None
        self.extract.changed.connect(self.run)
        self.view.changed.connect(self._show_gallery)
        self.patch.changed.connect(self._go_to)
        self.accept.changed.connect(lambda: self.set_status("kept"))
        self.reject.changed.connect(lambda: self.set_status(REJECTED))
        self.points.changed.connect(self._on_points)
        self.image.changed.connect(self._on_points)
        viewer.layers.events.inserted.connect(self._on_layers)
        viewer.layers.events.removed.connect(self._on_layers)
        self._on_layers()
        self._on_points()

    def _on_points(self, *_) -> None:
        img, pts = self.image.value, self.points.value
        self._follow(pts)
        px = None
        if img is not None:
            scale = float(img.scale[-1])
            px = (img.metadata or {}).get("pixel_size_um") or (scale if scale != 1.0 else None)
        r = None if pts is None else (pts.metadata or {}).get("psf_radius_px")
        if r is None and img is not None:
            r = (img.metadata or {}).get("psf_radius")
        self.radius.set_calibration(px, r)

    def run(self, *_) -> None:
        """Extract the patches of the beads of the Points layer (in a worker thread)."""
        img, pts = self.image.value, self.points.value
        if img is None or pts is None:
            self.task.status.value = "Choose an image and its beads (Pick beads first)."
            return
        got = self._bead_plane(img, pts)
        if got is None:
            return
        plane, frame = got
        ensure_bead_features(pts)
        beads, ids = beads_from_points(pts, frame)
        gen = iter_patch_review(plane, beads, self.radius.pixels)

        def on_result(review: PatchReview) -> None:
            self.review, self._ids, self._frame = review, ids[review.index], frame
            self._show_gallery()
            self.patch.max = len(review) - 1
            focus_on_step(self._viewer, "Review", self.image.value)
            self.patch.enabled = self.accept.enabled = self.reject.enabled = True
            self.task.status.value = (f"{len(review)} patches right of the image; click one, "
                                      f"or set 'patch'.")
            self._go_to()

        self.task.run(gen, on_result)

    def _show_gallery(self, *_) -> None:
        if self.review is None:
            return
        stack = self.review.views[self.view.value]
        layer = show_layers(self._viewer, gallery_layers(stack, self._frame,
                                                       view=self.view.value),
                            step="Review")[0]
        if self._on_click not in layer.mouse_drag_callbacks:
            layer.mouse_drag_callbacks.append(self._on_click)
        self._outline()

    def _on_click(self, layer, event) -> None:
        """A click on a patch of the gallery puts that bead on display."""
        k = gallery_index(layer, event.position)
        if k is not None and 0 <= k < len(self.review or ()):
            self.patch.value = k

    def current(self) -> int:
        """Index of the patch on display."""
        return int(self.patch.value)

    def _go_to(self, *_) -> None:
        if self.review is None:
            return
        self._outline()
        self._describe(self.current())

    def _outline(self) -> None:
        """A rectangle around the patch on display in the gallery."""
        gallery = find_layer(self._viewer, GALLERY, "image")
        if self.review is None or gallery is None:
            return
        corners = gallery_cell(gallery, self.current())
        rect = np.array([corners[0], [corners[0][0], corners[1][1]], corners[1],
                         [corners[1][0], corners[0][1]]])
        show_layers(self._viewer, [(rect[None], {
            "name": CURRENT, "shape_type": "rectangle", "edge_color": "#ffe135",
            "face_color": "transparent", "edge_width": 2.0 * float(
                gallery.scale[-1]), **field_units(self._frame),
            "metadata": {"about": "the patch on display in Review"}}, "shapes")],
                    step="Review")

    def _status_of(self, bead_id: int) -> str:
        pts = self.points.value
        if pts is None:
            return "deleted"
        hit = np.flatnonzero(np.asarray(pts.features["id"]) == bead_id)
        return str(pts.features["status"].iloc[hit[0]]) if len(hit) else "deleted"

    def _describe(self, k: int) -> None:
        bead_id = int(self._ids[k])
        status = self._status_of(bead_id)
        flags = self.review.flags(k)
        z = self.review.zscore[k]
        # in the widget, not on the canvas: it would stay there through every later step
        self.info.value = (f"bead {bead_id} ({k + 1}/{len(self.review)}): "
                           f"{STATUS_MEANING.get(status, status)}"
                           + ("" if np.isnan(z) else f"; shape z-score {z:.1f}")
                           + ("\nflags: " + ", ".join(flags) if flags else "\nno flags"))
        pts = self.points.value
        if pts is not None:
            rows = np.flatnonzero(np.asarray(pts.features["id"]) == bead_id)
            pts.selected_data = set(rows.tolist())

    def set_status(self, status: str) -> None:
        """Accept ("kept") or reject the bead on display, in the Points layer."""
        if self.review is None or self.points.value is None:
            return
        set_statuses(self.points.value, [int(self._ids[self.current()])], [status])
        self._describe(self.current())
