"""Learn operator: end to end from detection to the saved model; cancel; errors."""

import numpy as np
import pytest

from conftest import wait_task
from napari_psfspace import load_operator
from napari_psfspace._layers import (
    BASIS,
    BEADS,
    HELDOUT_LAYER,
    PSF_AT,
    PSF_GRID,
    WEIGHT,
)
from napari_psfspace._layers.results import SHOWN_WEIGHTS
from napari_psfspace._widgets._learn_operator import LearnOperatorWidget
from napari_psfspace._widgets._pick_beads import PickBeadsWidget
from napari_psfspace._widgets._review_patches import ReviewPatchesWidget


def _detect(viewer, qtbot):
    pick = PickBeadsWidget(viewer)
    pick.detect.clicked()
    wait_task(qtbot, pick.task)
    return viewer.layers[BEADS]


def test_detect_reject_learn_save(viewer, qtbot, tmp_path):
    pts = _detect(viewer, qtbot)
    review = ReviewPatchesWidget(viewer)
    review.extract.clicked()
    wait_task(qtbot, review.task)
    review.patch.value = 0
    rejected_id = int(review._ids[0])
    review.reject.clicked()

    w = LearnOperatorWidget(viewer)
    assert w.points.value is pts
    path = tmp_path / "model.npz"
    w.save_path.value = path
    w.learn.clicked()
    wait_task(qtbot, w.task)

    for name in (PSF_GRID, BASIS, WEIGHT.format(1), HELDOUT_LAYER):
        assert name in viewer.layers, name
    op = load_operator(path)
    image = viewer.layers["beads image"]
    assert op.image_shape == image.data.shape
    assert np.isclose(op.metadata["pixel_size_um"], image.scale[-1])
    # the basis a 2-D mosaic, a weight map a layer, each on the image's field: no axis
    # shared with the image
    basis = viewer.layers[BASIS]
    maps = [viewer.layers[WEIGHT.format(i + 1)] for i in range(op.n_psf)]
    assert basis.data.ndim == 2 and viewer.dims.ndim == 2
    assert all(m.data.ndim == 2 for m in maps)
    assert [m.visible for m in maps] == [i < SHOWN_WEIGHTS for i in range(op.n_psf)]
    cols = int(np.ceil(np.sqrt(op.n_psf)))
    p = op.psf_size
    assert basis.data.shape[1] == cols * (p + 2) - 2
    first = op.basis[0] / np.abs(op.basis[0]).max()
    assert np.allclose(basis.data[:p, :p], first, atol=1e-6)
    field = np.asarray(image.extent.world)
    for layer in (basis, viewer.layers[PSF_GRID], *maps):
        box = np.asarray(layer.extent.world)
        assert np.all(box[0] >= field[0] - 1e-6) and np.all(box[1] <= field[1] + 1e-6)
    # the rejected bead was not used; the Points layer got the final statuses
    used = np.asarray(op.metadata["bead_positions"])
    row = np.flatnonzero(pts.features["id"] == rejected_id)[0]
    assert pts.features["status"].iloc[row] == "rejected"
    assert np.min(np.hypot(*(used - pts.data[row]).T)) > 1.0
    assert op.metadata["n_beads_used"] <= int((pts.features["status"] == "kept").sum())
    assert "held-out error" in w.result.value and str(path) in w.result.value
    # the basis size: each size tried with its held-out error, the chosen one marked
    sizes = w.sizes.value["data"]
    errors = op.metadata["heldout_error_by_n_psf"]
    assert [int(r[0]) for r in sizes] == list(range(1, len(errors) + 1))
    assert [r[0] for r in sizes if r[2] == "chosen"] == [str(op.n_psf)]
    # motion blur is looked for on every model (a still sample: nothing found)
    assert op.metadata["motion"]["detected"] is False and not w.remove_motion.value

    # in micrometres, as the radius (the image has a 0.065 um pixel)
    assert "µm" in w.psf_unit.value and "µm" in w.radius.value_edit.label
    w.psf_y.value, w.psf_x.value = 3.25, 19.5  # 50 and 300 px
    w.show_psf.clicked()
    # at most rounded once to float32 for the layer
    u32 = np.finfo(np.float32).eps / 2
    assert np.allclose(viewer.layers[PSF_AT].data, op.psf_at(50.0, 300.0), rtol=u32, atol=0)


def test_deleted_and_moved_points_are_respected(viewer, qtbot, tmp_path):
    pts = _detect(viewer, qtbot)
    kept = np.flatnonzero(pts.features["status"] == "kept")
    pts.selected_data = {int(kept[0])}
    gone = pts.data[kept[0]].copy()
    pts.remove_selected()
    w = LearnOperatorWidget(viewer)
    w.save_path.value = tmp_path / "m.npz"
    w.learn.clicked()
    wait_task(qtbot, w.task)
    used = np.asarray(load_operator(tmp_path / "m.npz").metadata["bead_positions"])
    assert np.min(np.hypot(*(used - gone).T)) > 3.0


def test_cancel_leaves_viewer_usable_and_file_untouched(viewer, qtbot, tmp_path):
    _detect(viewer, qtbot)
    path = tmp_path / "model.npz"
    path.write_bytes(b"previous model")
    w = LearnOperatorWidget(viewer)
    w.save_path.value = path
    n_layers = len(viewer.layers)
    w.learn.clicked()
    assert w.task.running and not w.learn.enabled
    with qtbot.waitSignal(w.task.worker.aborted, timeout=30_000):
        w.task.cancel.clicked()
    wait_task(qtbot, w.task)
    assert path.read_bytes() == b"previous model"
    assert len(viewer.layers) == n_layers and PSF_GRID not in viewer.layers
    assert "cancelled" in w.task.status.value
    assert w.learn.enabled
    assert not list(tmp_path.glob(".*tmp"))
    # still usable: learn again
    w.learn.clicked()
    wait_task(qtbot, w.task)
    assert PSF_GRID in viewer.layers
    assert load_operator(path).n_psf >= 1


def test_three_beads_give_a_shift_invariant_model_and_say_why(viewer, qtbot, tmp_path):
    pts = _detect(viewer, qtbot)
    pts.selected_data = set(range(len(pts.data) - 3))
    pts.remove_selected()
    w = LearnOperatorWidget(viewer)
    w.save_path.value = tmp_path / "m.npz"
    w.learn.clicked()
    wait_task(qtbot, w.task)
    assert w.operator is not None and w.operator.metadata["field_model"] in (
        "shift-invariant", "affine")
    assert "3 usable beads" in w.result.value
    if w.operator.metadata["field_model"] == "shift-invariant":
        assert "The model is shift-invariant" in w.result.value
    assert (tmp_path / "m.npz").exists()


def test_no_usable_bead_is_a_notification(viewer, qtbot, tmp_path, monkeypatch):
    import napari_psfspace._widgets._worker as worker_mod

    shown = []
    monkeypatch.setattr(worker_mod, "show_error", shown.append)
    pts = _detect(viewer, qtbot)
    pts.features["status"] = "rejected"
    w = LearnOperatorWidget(viewer)
    w.save_path.value = tmp_path / "m.npz"
    w.learn.clicked()
    wait_task(qtbot, w.task)
    assert len(shown) == 1 and "No usable bead" in shown[0]
    assert not (tmp_path / "m.npz").exists()


def test_stack_uses_the_detection_slice_and_radius(make_napari_viewer, qtbot, bead_image,
                                                   tmp_path):
    """A user's z-stack (beads in focus on one slice only), widgets opened before the
    detection, and the slider moved away (e.g. by the patch gallery) before learning:
    the operator must come from the detection slice, with the detection's radius."""
    image, truth = bead_image
    flat = np.full_like(image, int(np.median(image)))
    stack = np.stack([flat, image, flat])
    v = make_napari_viewer()
    v.add_image(stack, name="stack")
    pick, learn = PickBeadsWidget(v), LearnOperatorWidget(v)
    v.dims.set_point(0, 1)
    pick.radius.value_edit.value = float(truth.psf_radius)
    pick.detect.clicked()
    wait_task(qtbot, pick.task)
    assert v.layers[BEADS].metadata["slice"] == 1
    assert learn.radius.pixels == pytest.approx(truth.psf_radius)  # followed the beads
    v.dims.set_point(0, 0)  # an empty slice on display
    learn.save_path.value = tmp_path / "m.npz"
    learn.learn.clicked()
    wait_task(qtbot, learn.task)
    op = load_operator(tmp_path / "m.npz")
    assert op.metadata["n_beads_used"] >= 15
    assert op.metadata["psf_radius"] == pytest.approx(truth.psf_radius)


def test_four_beads_give_one_psf_and_each_beads_own_fwhm(make_napari_viewer, qtbot):
    """Below the held-out minimum the model is one PSF: the dock says the field is not
    mapped, no weight map is drawn, and each bead's own FWHM is a point at the bead, in
    µm, within a fifth of the truth's (the model's PSF at the centre, fitted alike)."""
    import napari_psfspace as ps
    from conftest import calibrated_viewer
    from napari_psfspace._layers import BEAD_FWHM
    from napari_psfspace.core.common.measures import lateral_measures
    from napari_psfspace.core.model.fewbeads import TOO_FEW

    image, truth = ps.simulate_beads((256, 256), 4, min_separation=60, seed=1)
    v = calibrated_viewer(make_napari_viewer, image, truth, "four beads")
    w = LearnOperatorWidget(v)
    w.learn.clicked()
    wait_task(qtbot, w.task)
    assert w.operator.n_psf == 1 and TOO_FEW in w.result.value
    assert WEIGHT.format(1) not in v.layers
    pts = v.layers[f"{BEAD_FWHM} (µm)"]
    assert len(pts.data) == w.operator.metadata["n_beads_used"] <= 4
    px = truth.optics.pixel_size
    own = lateral_measures(w.operator.psf_at(128, 128))["fwhm_lateral"] * px
    assert np.all(np.abs(pts.features["fwhm"] / own - 1) < 0.2), (list(pts.features["fwhm"]),
                                                                    own)
