"""Pick beads: detection fills an editable Points layer coloured by status."""

import numpy as np
import pytest

from conftest import wait_task
from napari_psfspace._layers import BEADS, STATUS_COLORS
from napari_psfspace._widgets._pick_beads import PickBeadsWidget


def test_radius_in_micrometres_for_a_calibrated_image(viewer):
    w = PickBeadsWidget(viewer)
    assert w.image.value is viewer.layers["beads image"]
    assert "µm" in w.radius.value_edit.label
    assert np.isclose(w.radius.pixels, 14.0, atol=0.05)
    viewer.add_image(np.zeros((64, 64)), name="uncalibrated")
    w.image.value = viewer.layers["uncalibrated"]
    assert "px" in w.radius.value_edit.label


def test_detect_fills_points_layer_with_features_and_colours(viewer, qtbot):
    w = PickBeadsWidget(viewer)
    w.detect.clicked()
    wait_task(qtbot, w.task)
    pts = viewer.layers[BEADS]
    assert len(pts.data) >= 20
    assert list(pts.features.columns[:3]) == ["id", "amplitude", "status"]
    assert set(pts.features["status"]) <= {"kept", "border", "neighbour", "saturated"}
    assert np.array_equal(pts.features["id"], np.arange(len(pts.data)))
    kept = np.flatnonzero(pts.features["status"] == "kept")[0]
    from napari.utils.colormaps.standardize_color import transform_color

    assert np.allclose(pts.face_color[kept], transform_color(STATUS_COLORS["kept"])[0])
    assert np.allclose(pts.scale, viewer.layers["beads image"].scale)
    assert "kept" in w.task.status.value

    # a point added by hand is kept, with a new id
    pts.add([100.0, 100.0])
    assert pts.features["status"].iloc[-1] == "kept"
    assert pts.features["id"].iloc[-1] == len(pts.data) - 1
    assert pts.features["id"].is_unique


def test_detection_error_is_a_notification_naming_threshold(make_napari_viewer, qtbot,
                                                           noise_image, monkeypatch):
    shown = []
    import napari_psfspace._widgets._worker as worker_mod

    monkeypatch.setattr(worker_mod, "show_error", shown.append)
    v = make_napari_viewer()
    v.add_image(noise_image, name="noise")
    w = PickBeadsWidget(v)
    w.threshold.value = 50.0
    w.detect.clicked()
    wait_task(qtbot, w.task)
    assert len(shown) == 1 and "`threshold`" in shown[0]
    assert "Traceback" not in shown[0]
    assert BEADS not in v.layers
    assert w.detect.enabled  # usable again


def test_suggest_radius_sets_a_usable_radius(make_napari_viewer, qtbot, bead_image):
    """A user's own image without metadata: the radius starts at the default; Suggest
    measures it (the sample's true radius is 14 px; the suggestion is within range)."""
    image, truth = bead_image
    v = make_napari_viewer()
    v.add_image(image, name="my beads")
    w = PickBeadsWidget(v)
    assert "px" in w.radius.value_edit.label
    w.suggest.clicked()
    wait_task(qtbot, w.task)
    assert "suggested PSF radius" in w.task.status.value
    assert 0.4 * truth.psf_radius <= w.radius.pixels <= 1.6 * truth.psf_radius


def test_suggest_radius_on_a_slice_follows_its_neighbours(make_napari_viewer, qtbot,
                                                         bead_image):
    """On a stack's slice the suggestion is the median of the slice's and its
    neighbours' readings; a slice that jumps (blurred here) says so in the status line."""
    from scipy import ndimage as ndi

    from napari_psfspace.core.beads.slice_radius import suggest_slice_radius

    image, _ = bead_image
    stack = np.stack([image, ndi.gaussian_filter(image.astype(float), 4.0), image])
    v = make_napari_viewer()
    v.add_image(stack.astype(np.float32), name="stack")
    v.dims.set_point(0, 1)
    w = PickBeadsWidget(v)
    w.suggest.clicked()
    wait_task(qtbot, w.task)
    want = suggest_slice_radius(stack.astype(np.float32), 1)
    assert w.radius.pixels == pytest.approx(want.radius)
    assert "slice 1 alone reads" in w.task.status.value


def test_bead_diameter_in_nanometres_reaches_the_learnt_model(viewer, qtbot):
    """200 nm beads at the image's 65 nm pixels: 3.08 px, recorded with the beads and
    divided out of the PSFs the Learn widget makes from them."""
    from napari_psfspace._widgets._learn_operator import LearnOperatorWidget

    w = PickBeadsWidget(viewer)
    w.bead_diameter.value = 200.0
    w.detect.clicked()
    wait_task(qtbot, w.task)
    meta = viewer.layers[BEADS].metadata
    assert meta["bead_diameter_nm"] == 200.0
    assert np.isclose(meta["bead_diameter_px"], 0.2 / 0.065)
    learn = LearnOperatorWidget(viewer)
    learn.save_path.value = ""
    learn.learn.clicked()
    wait_task(qtbot, learn.task)
    corr = learn.operator.metadata["bead_correction"]
    assert np.isclose(corr["diameter_px"], 0.2 / 0.065)
    assert "Bead size corrected" in learn.result.value


def test_bead_diameter_without_pixel_size_is_refused(make_napari_viewer, qtbot, bead_image,
                                                     monkeypatch):
    from napari.utils import notifications

    shown = []
    monkeypatch.setattr(notifications, "show_error", shown.append)
    v = make_napari_viewer()
    v.add_image(bead_image[0], name="uncalibrated")
    w = PickBeadsWidget(v)
    w.bead_diameter.value = 200.0
    w.detect.clicked()
    assert len(shown) == 1 and "pixel size" in shown[0]
    assert BEADS not in v.layers


def test_hot_pixels_are_shown_beside_the_beads(make_napari_viewer, qtbot):
    from napari_psfspace._layers import HOT_PIXELS
    from napari_psfspace.core.simulation import simulate_beads

    image, truth = simulate_beads((384, 384), 25, seed=3, effects={"hot_pixels": 20})
    v = make_napari_viewer()
    v.add_image(image, name="hot")
    w = PickBeadsWidget(v)
    w.detect.clicked()
    wait_task(qtbot, w.task)
    assert HOT_PIXELS in v.layers and BEADS in v.layers
    assert len(v.layers[HOT_PIXELS].data) >= 18  # 20 injected
    assert "hot pixel(s) masked" in w.task.status.value
    assert v.layers.selection.active is v.layers[BEADS]
    # a detection on a clean image empties the layer rather than leave stale points
    v.layers["hot"].data = truth_clean_image(image, truth)
    w.detect.clicked()
    wait_task(qtbot, w.task)
    assert len(v.layers[HOT_PIXELS].data) == 0


def truth_clean_image(image, truth):
    """The image without its simulated hot pixels."""
    clean = image.copy()
    where = truth.effects["hot_pixel_positions"]
    clean[where[:, 0], where[:, 1]] = np.median(image)
    return clean
