"""One accuracy figure (core/diagnosis/metric.py): the panel's Model and Diagnose steps,
``psfspace estimate`` and ``psfspace diagnose`` (the command, as a subprocess) and
``report.json`` give the same held-out error for one image."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from conftest import wait_task
from napari_psfspace._layers import BEADS, find_layer
from napari_psfspace.core.diagnosis.metric import NAME

PLUGIN = "napari-psfspace"


def test_the_held_out_error_is_one_number_everywhere(make_napari_viewer, bead_image, qtbot,
                                                     tmp_path):
    from napari_psfspace.io import write_tiff

    image, truth = bead_image
    path = tmp_path / "beads.tif"
    write_tiff(path, np.asarray(image, np.float32), pixel_size=truth.optics.pixel_size)
    r = float(truth.psf_radius)
    v = make_napari_viewer()
    v.open(str(path), plugin=PLUGIN)
    _, panel = v.window.add_plugin_dock_widget(PLUGIN, "PSF space")
    pick, learn, diag = (panel.steps[s] for s in ("Beads", "Model", "Diagnose"))
    # the user's path: beads detected (as the commands detect them), then Model and
    # Diagnose on that beads layer
    pick.radius.set_calibration(pick.radius.pixel_size, r)
    pick.detect.clicked()
    wait_task(qtbot, pick.task)
    points = find_layer(v, BEADS, "points")  # "beads [1]": the image is "beads"
    names = [layer.name for layer in v.layers]
    pick.detect.clicked()  # again: the renamed layer is found and updated, not doubled
    wait_task(qtbot, pick.task)
    assert [layer.name for layer in v.layers] == names and find_layer(v, BEADS) is points
    for step in (learn, diag):
        assert step.points.value is points and step.radius.pixels == r
    learn.learn.clicked()
    wait_task(qtbot, learn.task, timeout=120_000)
    diag.diagnose.clicked()
    wait_task(qtbot, diag.task, timeout=120_000)
    in_model = learn.operator.metadata["heldout_error"]
    in_diagnose = diag.diagnosis.heldout
    # the panel shows it, under the metric's one name
    assert f"{NAME} {in_model['error']:.4g}" in learn.result.value
    assert f"{NAME} {in_diagnose.error:.4g}" in diag.result.value

    report = tmp_path / "report"
    run = subprocess.run([sys.executable, "-m", "napari_psfspace.cli", "diagnose",
                          str(path), "--report", str(report), "--psf-radius", str(r), "-q"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    in_json = json.loads((report / "report.json").read_text())["heldout_error"]
    run = subprocess.run([sys.executable, "-m", "napari_psfspace.cli", "estimate", str(path),
                          "-o", str(tmp_path / "model.npz"), "--psf-radius", str(r), "-q"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert f"{NAME} {in_json['error']:.4g}" in run.stdout

    # the same code on the same pixels and beads: equal to rounding (threads may sum in
    # another order: 1e-12 relative is far below the 4 digits printed)
    for other in (in_diagnose.error, in_json["error"]):
        assert np.isclose(in_model["error"], other, rtol=1e-12, atol=0)
    assert np.isclose(in_model["noise_floor"], in_json["noise_floor"], rtol=1e-12, atol=0)
    assert in_model["n_beads"] == in_diagnose.n_beads == in_json["n_beads"]
