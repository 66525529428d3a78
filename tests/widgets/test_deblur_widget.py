"""Deblur: a family from the viewer with clicked beads, a model file; cancel; errors."""

import numpy as np
import pytest

from conftest import wait_task
from napari_psfspace._layers import MORE_BEADS, SUBSPACE_KEY
from napari_psfspace._widgets._deblur import (
    MOST_POINTS,
    POINT_SIZE,
    SMALLEST_POINT,
    SMOOTH,
    SOURCES,
    SPARSE,
    SPARSE_POINTS,
    DeblurWidget,
)
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.simulation.stacks import simulate_stack


@pytest.fixture(scope="module")
def family():
    images, truths, _ = simulate_stack(6, (256, 256), 12, seed=5)
    r = int(np.median([t.psf_radius for t in truths]))
    sub = estimate_family(images[:5], psf_radius=r, holdout=None)
    return sub, images[5], truths[5]


def test_blind_deblur_from_clicked_beads(make_napari_viewer, qtbot, family):
    sub, image, truth = family
    v = make_napari_viewer()
    v.add_image(image, name="sample", scale=(0.065, 0.065))
    v.add_image(np.zeros((2, 2)), name="holder", metadata={SUBSPACE_KEY: sub})
    clicked = truth.positions[:5] * 0.065  # world coordinates, as napari stores them
    v.add_points(clicked, name="my beads")
    w = DeblurWidget(v)
    w.image.value = v.layers["sample"]
    w.source.value = SOURCES[1]
    assert w.model() is sub
    w.points.value = v.layers["my beads"]
    w.max_iter.value = 60
    w.refit.value = True  # the points' flux refitted after the deblurring
    w.run_button.clicked()
    wait_task(qtbot, w.task, timeout=120_000)
    assert w.last.parameters["debias"] and w.last.parameters["debias_iterations"] > 0
    sparse, smooth = v.layers[f"{SPARSE} (image units)"], v.layers[f"{SMOOTH} (image units)"]
    assert sparse.data.shape == image.shape and np.allclose(sparse.scale, (0.065, 0.065))
    assert sparse.data.min() >= 0 and smooth.data.min() >= 0
    assert "identified from" in w.result.value
    # the operator was identified from the clicked beads, taken to pixels and centred
    used = np.asarray(w.operator.metadata["identification"]["positions"])
    assert 1 <= len(used) <= 5
    assert np.all(np.min(np.hypot(*(used[:, None] - truth.positions[None, :5]).transpose(
        2, 0, 1)), axis=1) < 1.0)
    # the points come back where the beads are
    for y, x in truth.positions[:5]:
        yy, xx = int(round(y)), int(round(x))
        assert sparse.data[yy - 2:yy + 3, xx - 2:xx + 3].sum() > 0
    # visible at the home view: the sparse image's contrast reaches its typical point
    # (its top under the brightest, above the median of its nonzero pixels), and each
    # nonzero pixel is also a point over it, at least SMALLEST_POINT of POINT_SIZE of the
    # field wide
    nz = sparse.data[sparse.data > 0]
    lo, hi = sparse.contrast_limits
    assert np.median(nz) < hi <= nz.max()
    pts = v.layers[f"{SPARSE_POINTS} (image units)"]
    assert len(pts.data) == min(len(nz), MOST_POINTS)
    field = max(image.shape) * 0.065
    assert np.min(pts.size) >= SMALLEST_POINT * POINT_SIZE * field * (1 - 1e-9)
    # the input and the smooth part side by side at one contrast, from the input's
    # values: its bright beads do not set the top (the 99.9th percentile is under them)
    shown = v.layers[w.image.value.name]
    assert np.allclose(smooth.contrast_limits, shown.contrast_limits)
    assert shown.contrast_limits[1] < float(np.max(shown.data))
    np.testing.assert_allclose(pts.data_to_world(pts.data[np.argmax(pts.features["amplitude"])]),
                               np.asarray(np.unravel_index(np.argmax(sparse.data),
                                                           sparse.data.shape)) * 0.065
                               + np.asarray(sparse.translate), atol=1e-9)
    # where one more bead would help most: a cross on the input, in its world units
    info = w.operator.metadata["identification"]
    cross = v.layers[MORE_BEADS]
    np.testing.assert_allclose(cross.data_to_world(cross.data[0]),
                               np.asarray(info["more_beads_at"]) * 0.065, rtol=1e-9)
    assert "where one more bead would help most" in w.result.value


def test_model_file_cancel_and_errors(make_napari_viewer, qtbot, family, tmp_path,
                                      monkeypatch):
    import napari_psfspace._widgets._deblur as mod

    shown = []
    monkeypatch.setattr(mod, "show_error", shown.append)
    sub, image, _ = family
    v = make_napari_viewer()
    v.add_image(image, name="sample")
    w = DeblurWidget(v)
    w.run_button.clicked()
    assert "file" in shown[-1]
    w.source.value = SOURCES[1]
    w.run_button.clicked()
    assert "in the viewer" in shown[-1]
    path = tmp_path / "model.npz"
    sub.operator(0).save(path)
    w.source.value = SOURCES[0]
    w.path.value = path
    n = len(v.layers)
    w.max_iter.value = 100000
    w.run_button.clicked()
    assert w.task.running
    with qtbot.waitSignal(w.task.worker.aborted, timeout=60_000):
        w.task.cancel.clicked()
    wait_task(qtbot, w.task)
    assert len(v.layers) == n and "cancelled" in w.task.status.value
    w.max_iter.value = 30
    w.run_button.clicked()
    wait_task(qtbot, w.task, timeout=120_000)
    assert f"{SPARSE} (image units)" in v.layers and "the model as it is" in w.result.value
    from napari_psfspace.core.common.device import gpu_status

    on_gpu = gpu_status()[0]
    assert ("on the GPU" if on_gpu else "on the CPU") in w.result.value
    assert w.last.parameters["device"] == ("gpu" if on_gpu else "cpu")
    if not on_gpu:  # a GPU asked for where there is none: one line, before any work
        w.device.value = "gpu"
        w.run_button.clicked()
        assert not w.task.running
        assert "\n" not in shown[-1] and "napari-psfspace[gpu]" in shown[-1], shown[-1]
