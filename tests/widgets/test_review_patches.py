"""Review patches: a gallery stack with flags; accept / reject edit the Points layer."""

import numpy as np

from conftest import wait_task
from napari_psfspace._widgets._layers import BEADS, GALLERY
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
    assert gallery.data.shape[0] == n and gallery.data.shape[1] == gallery.data.shape[2]
    raw = np.array(gallery.data)
    w.view.value = "windowed"
    assert gallery.metadata["view"] == "windowed"
    assert not np.allclose(raw, gallery.data)

    w.patch.value = 2
    assert int(round(viewer.dims.point[0])) == 2
    assert "bead" in w.info.value and "flags" in w.info.value or "no flags" in w.info.value
    bead_id = int(w._ids[2])
    w.reject.clicked()
    row = np.flatnonzero(pts.features["id"] == bead_id)[0]
    assert pts.features["status"].iloc[row] == "rejected"
    assert "rejected" in w.info.value
    w.accept.clicked()
    assert pts.features["status"].iloc[row] == "kept"

    # moving the dims slider moves the widget
    viewer.dims.set_point(0, 4)
    assert w.patch.value == 4
