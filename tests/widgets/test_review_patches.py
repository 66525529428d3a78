"""Review patches: a gallery stack with flags; accept / reject edit the Points layer."""

import numpy as np

from conftest import wait_task
from napari_psfspace._layers import (
    BEADS,
    CURRENT,
    GALLERY,
    gallery_cell,
    gallery_index,
)
from napari_psfspace._widgets._pick_beads import PickBeadsWidget
from napari_psfspace._widgets._review_patches import ReviewPatchesWidget


def test_review_gallery_views_and_reject(viewer, qtbot):
    pick = PickBeadsWidget(viewer)
    pick.detect.clicked()
    wait_task(qtbot, pick.task)
    pts = viewer.layers[BEADS]
    w = ReviewPatchesWidget(viewer)
    assert w.points.value is pts
    assert np.isclose(w.radius.pixels, 14.0, atol=0.05)
    w.extract.clicked()
    wait_task(qtbot, w.task)
    gallery = viewer.layers[GALLERY]
    n = int(np.count_nonzero(pts.features["status"] != "border"))
    # one 2-D mosaic: no axis shared with the data (a stack's slider stays put)
    assert gallery.data.ndim == 2 and viewer.dims.ndim == 2
    cols, p = gallery.metadata["columns"], gallery.metadata["patch"]
    assert cols * int(np.ceil(n / cols)) >= n > cols * (int(np.ceil(n / cols)) - 1)
    raw = np.array(gallery.data)
    w.view.value = "windowed"
    assert gallery.metadata["view"] == "windowed"
    assert not np.allclose(raw, gallery.data)

    w.patch.value = 2
    # the patch on display is outlined: its cell, and patch 2's pixels inside it
    box = viewer.layers[CURRENT].data[0]
    centre = box.mean(axis=0)
    assert gallery_index(gallery, centre) == 2
    tile = w.review.views["windowed"][2]
    r0 = (centre - np.asarray(gallery.translate)) / np.asarray(gallery.scale)
    y, x = (int(round(v - (p - 1) / 2)) for v in r0)
    got = np.asarray(gallery.data)[y:y + p, x:x + p]
    assert np.allclose(got, tile / np.abs(tile).max(), atol=1e-6)
    assert "bead" in w.info.value and "flags" in w.info.value or "no flags" in w.info.value
    assert "z-score" in w.info.value or "z =" not in w.info.value
    bead_id = int(w._ids[2])
    w.reject.clicked()
    row = np.flatnonzero(pts.features["id"] == bead_id)[0]
    assert pts.features["status"].iloc[row] == "rejected"
    assert "rejected" in w.info.value
    w.accept.clicked()
    assert pts.features["status"].iloc[row] == "kept"

    # a click on a patch of the gallery puts that bead on display; between patches, none
    class Click:
        position = gallery_cell(gallery, 4).mean(axis=0)

    w._on_click(gallery, Click())
    assert w.patch.value == 4
    Click.position = np.asarray(gallery.translate) - 5 * np.asarray(gallery.scale)
    w._on_click(gallery, Click())
    assert w.patch.value == 4


def test_the_gallery_leaves_a_stacks_slider_where_it_was(make_napari_viewer, qtbot,
                                                         bead_image):
    image, truth = bead_image
    v = make_napari_viewer()
    v.add_image(np.stack([image * 0.5, image, image * 0.5]), name="stack")
    v.dims.set_point(0, 1)
    pick = PickBeadsWidget(v)
    pick.radius.set_calibration(None, truth.psf_radius)
    pick.detect.clicked()
    wait_task(qtbot, pick.task)
    w = ReviewPatchesWidget(v)
    w.extract.clicked()
    wait_task(qtbot, w.task)
    w.patch.value = 2
    assert v.dims.point[0] == 1  # was set to the patch's index (the image went black)
