"""Diagnose widget: end to end on an image with hot pixels; report; cancel."""

import json

import numpy as np
import pytest

from conftest import calibrated_viewer, wait_task
from napari_psfspace._widgets._diagnose import (
    MAP_AFTER,
    MAP_BEFORE,
    MEAN_AFTER,
    MEAN_BEFORE,
    DiagnoseWidget,
)


@pytest.fixture(scope="module")
def hot_image():
    from napari_psfspace.core.simulation import simulate_beads

    return simulate_beads((384, 384), 30, seed=1, effects={"hot_pixels": 30})


@pytest.fixture
def hot_viewer(make_napari_viewer, hot_image):
    return calibrated_viewer(make_napari_viewer, *hot_image, "hot image")


def test_diagnose_shows_steps_maps_and_writes_report(hot_viewer, qtbot, tmp_path, hot_image):
    _, truth = hot_image
    w = DiagnoseWidget(hot_viewer)
    assert w.image.value is hot_viewer.layers["hot image"]
    assert w.radius.pixels == pytest.approx(truth.psf_radius)
    camera = (w.gain, w.offset, w.read_noise)
    assert all(c.native.isHidden() for c in camera)  # off by default
    w.camera.value = True
    assert not any(c.native.isHidden() for c in camera)
    w.camera.value = False
    w.remove_motion.value = True  # asked for, but this image holds no smear
    w.report_dir.value = tmp_path / "report"
    w.diagnose.clicked()
    wait_task(qtbot, w.task, timeout=60_000)

    d = w.diagnosis
    assert d is not None
    table = w.table.to_dataframe()
    # the dock's words and columns (the report holds every column)
    assert [c.replace("\n", " ") for c in table.columns] == [
        "effect", "held-out error", "misfit / noise", "decision"]
    native = w.table.native
    w.native.show()
    native.resize(360, 300)  # the dock's width, less its margins
    qtbot.wait(50)
    assert native.horizontalHeader().length() <= native.viewport().width()  # no sideways
    assert "chi2" not in w.result.value and "misfit / noise" in w.result.value
    # each cell shows the report's text, its numbers to three digits (the baseline's
    # error "0.05516" is "0.0552", not a float rewritten as "5.516e-02"), the effects in
    # words
    from napari_psfspace._widgets._diagnose import dock_cell
    from napari_psfspace.report import steps_table

    assert dock_cell("0.05516 -> 0.004393") == "0.0552\n-> 0.00439"
    assert dock_cell("hot_pixels") == "hot pixels"
    report = steps_table(d)
    for i, row in enumerate(report):
        assert native.item(i, 1).text() == dock_cell(row[5])
        assert native.item(i, 2).text() == dock_cell(row[6])
        assert native.item(i, 0).text() == row[0].replace("_", " ")
    assert len(table) == len(d.steps)
    effects = table["effect"].tolist()
    assert effects[0] == "baseline"
    # the residual tests significant on either model, each row its strength over its
    # threshold on the plain and the final model
    tests = w.tests.value["data"]
    plain = [t.name.replace("_", " ") for t in d.analysis_before.significant()]
    assert [r[0] for r in tests][:len(plain)] == plain
    assert all(float(r[1]) > 1 for r in tests[:len(plain)])
    # every step tried is a row, with its decision
    for row, step in zip(table.itertuples(), d.steps, strict=True):
        if step.effect:
            assert row.decision == ("kept" if step.accepted else "rejected")
    # the hot pixels were masked at detection, and the summary says so
    assert len(d.hot_pixels) >= 27
    assert f"{len(d.hot_pixels)} hot pixel(s) masked" in w.result.value
    assert "added:" in w.result.value and "noise floor" in w.result.value

    image = hot_viewer.layers["hot image"]
    for name in (MAP_BEFORE, MAP_AFTER, MEAN_BEFORE, MEAN_AFTER):
        assert name in hot_viewer.layers, name
    m = hot_viewer.layers[MAP_BEFORE]
    # the maps cover the image's field (in world units), where it lies: napari's grid
    # shows them beside it
    for layer in (m, hot_viewer.layers[MAP_AFTER]):
        extent = np.asarray(layer.data.shape) * np.asarray(layer.scale)
        assert np.allclose(extent, np.asarray(image.data.shape) * np.asarray(image.scale),
                           rtol=0.05)
        corner = np.asarray(layer.translate) - np.asarray(layer.scale) / 2
        assert np.allclose(corner, -np.asarray(image.scale) / 2, atol=0.05 * extent.max())
    assert np.isfinite(m.data).any()
    assert hot_viewer.layers[MEAN_BEFORE].data.shape == d.crossfit_before.residuals.data.shape[1:]

    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["run"]["image"] == "hot image"
    assert report["run"]["pixel_size_um"] == pytest.approx(truth.optics.pixel_size)
    assert report["added"] == d.added
    assert report["options"]["remove_motion"] is True
    motion = report["model"]["motion"]
    assert motion["detected"] is False and "nothing removed" in motion["note"]
    assert (tmp_path / "report" / "residual_map_after.png").exists()
    assert "report.md" in w.result.value


def test_cancel_adds_nothing_and_widget_stays_usable(hot_viewer, qtbot, tmp_path):
    w = DiagnoseWidget(hot_viewer)
    w.report_dir.value = tmp_path / "report"
    n_layers = len(hot_viewer.layers)
    w.diagnose.clicked()
    assert w.task.running and not w.diagnose.enabled
    with qtbot.waitSignal(w.task.worker.aborted, timeout=60_000):
        w.task.cancel.clicked()
    wait_task(qtbot, w.task)
    assert "cancelled" in w.task.status.value
    assert len(hot_viewer.layers) == n_layers and MAP_BEFORE not in hot_viewer.layers
    assert w.diagnosis is None and not w.table.visible
    assert not (tmp_path / "report").exists()
    assert w.diagnose.enabled


def test_too_few_beads_is_a_notification(make_napari_viewer, qtbot, monkeypatch):
    import napari_psfspace._widgets._worker as worker_mod
    from napari_psfspace.core.simulation import simulate_beads

    shown = []
    monkeypatch.setattr(worker_mod, "show_error", shown.append)
    few, t = simulate_beads((256, 256), 4, seed=2)  # leave-one-bead-out needs 5
    v = make_napari_viewer()
    v.add_image(few, name="few", metadata={"psf_radius": t.psf_radius})
    w = DiagnoseWidget(v)
    w.diagnose.clicked()
    wait_task(qtbot, w.task)
    assert len(shown) == 1 and "Too few usable beads" in shown[0]
    assert MAP_BEFORE not in v.layers
