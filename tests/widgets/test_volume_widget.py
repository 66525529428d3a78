"""The 3D step (``_widgets/_volume``), opened as a user opens it: through the Plugins
menu's door at 1280 x 800, on a simulated bead z-stack with a voxel size."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import assert_maps_read_with_overlays, wait_task

PLUGIN = "napari-psfspace"


@pytest.fixture(scope="module")
def bead_stack():
    from napari_psfspace.core.simulation.focus import simulate_focus_series

    stack, series = simulate_focus_series((256, 256), 8, np.linspace(-0.4, 0.4, 5),
                                          seed=4)
    return stack, series


def test_learn_and_deblur_3d_twice_the_same_layers_and_cancel(make_napari_viewer, qtbot,
                                                              bead_stack, tmp_path):
    from napari_psfspace._widgets._volume import (
        DEBLURRED_3D,
        MAPS,
        OPERATOR_3D_KEY,
        PSF_GRID_3D,
        PSF_SECTIONS,
        PSF_SECTIONS_Y,
    )

    stack, series = bead_stack
    v = make_napari_viewer(show=True)
    v.window._qt_window.resize(1280, 800)
    _, w = v.window.add_plugin_dock_widget(PLUGIN, "7. 3D PSF and 3D deblur")
    assert type(w._viewer).__name__ == "PublicOnlyProxy"
    px = series.optics.pixel_size
    v.add_image(stack, name="bead stack", scale=(0.2, px, px))
    v.add_image(stack[0], name="a 2-D image")  # not offered: not a z-stack
    assert [name for name, _ in w._stacks()] == ["bead stack"]
    w.image.value = v.layers["bead stack"]
    assert w.radius.value_edit.label.endswith("(µm)")  # the stack is calibrated
    w.radius.set_calibration(w.radius.pixel_size, float(int(series.psf_radius.max())))
    names = None
    for _ in range(2):
        w.learn.clicked()
        wait_task(qtbot, w.learn_task, timeout=60_000)
        now = [layer.name for layer in v.layers]
        assert names is None or now == names  # a re-run updates, never piles up
        names = now
    # Report: no folder, one line; with one, the three files, the sampling the layer's
    w.report.clicked()
    assert w.report_task.status.value.startswith("report folder")
    w.report_dir.value = tmp_path / "qc"
    w.na.value, w.wavelength.value = series.optics.na, series.optics.wavelength * 1000
    w.report.clicked()
    wait_task(qtbot, w.report_task, timeout=60_000)
    import json

    rec = json.loads((tmp_path / "qc" / "qc.json").read_text(encoding="utf-8"))
    assert rec["sampling"]["z_step_nm"] == pytest.approx(200.0)
    assert rec["theory"] is not None and rec["centre_fwhm_lateral_nm"] > 0
    assert "qc.html" in w.report_result.value
    # the page drawn by Qt's HTML engine, offline: every figure decodes (data URIs)
    from qtpy.QtGui import QColor, QImage, QPainter, QTextDocument

    page = (tmp_path / "qc" / "qc.html").read_text(encoding="utf-8")
    figures = page.count('src="data:image/png;base64,')
    assert figures >= 4  # the average PSF and its SD, x-y and x-z (and the maps, if any)
    doc = QTextDocument()
    doc.setHtml(page)
    doc.setTextWidth(1100)
    img = QImage(1100, int(doc.size().height()), QImage.Format.Format_RGB32)
    img.fill(QColor("white"))
    painter = QPainter(img)
    doc.drawContents(painter)
    painter.end()
    rgb = np.frombuffer(img.constBits().asstring(img.sizeInBytes()) if hasattr(
        img.constBits(), "asstring") else bytes(img.constBits()), np.uint8)
    rgb = rgb.reshape(img.height(), -1, 4)[:, :1100, :3].astype(int)
    # colour (not grey) comes from the figures alone: a figure's colour bar is 18 x 240
    # pixels, most of them coloured, and its image adds thousands (a page whose images
    # do not decode holds a few hundred, in its green "pass" words)
    coloured = np.ptp(rgb, axis=2) > 40
    assert coloured.sum() >= figures * 5000, (coloured.sum(), figures)
    # Cancel during Learn 3D PSF: within 2 s, the layers as they were
    before = [layer.name for layer in v.layers]
    w.learn.clicked()
    w.learn_task.request_cancel()
    wait_task(qtbot, w.learn_task, timeout=2_000)
    assert w.learn_task.status.value.startswith("cancelled")
    assert [layer.name for layer in v.layers] == before
    grid = v.layers[f"{PSF_GRID_3D} (relative)"]
    op = grid.metadata[OPERATOR_3D_KEY]
    assert op is w.operator and grid.data.ndim == 3
    # on the stack's own planes: the z slider keeps the stack's length
    assert grid.data.shape[0] == stack.shape[0] and grid.translate[0] == 0.0
    assert grid.scale[0] == pytest.approx(0.2)
    sections = v.layers[f"{PSF_SECTIONS} (relative)"]
    assert f"{PSF_SECTIONS_Y} (relative)" in v.layers
    # the sections fit the field: no taller than the stack's
    height = np.ptp(np.asarray(sections.extent.world)[:, -2])
    assert height <= stack.shape[1] * px * (1 + 1e-6)
    # the maps in µm (the stack is calibrated), their unit in their names
    assert all(f"{label} (µm)" in v.layers for _, label, _ in MAPS)
    from napari_psfspace._layers import group_layers

    made = group_layers(v, "3D")
    assert_maps_read_with_overlays(v, {layer.name for layer in made})
    # every result on the stack's field: napari's grid puts each beside the stack
    raw = np.asarray(v.layers["bead stack"].extent.world)[:, -2:]
    for layer in (x for x in made if x.__class__.__name__ == "Image"):
        box = np.asarray(layer.extent.world)[:, -2:]
        tol = px  # napari's extents run between pixel centres: half a pixel each side
        assert np.all(box[0] >= raw[0] - tol) and np.all(box[1] <= raw[1] + tol), layer.name
    assert np.isfinite(v.layers[f"{MAPS[0][1]} (µm)"].data).all()
    # the lateral FWHM where the optics put it: 1 to 1.6x the Airy disk's (the grid's
    # PSFs carry the field's aberrations; a map in px would read 3-6 here)
    from napari_psfspace.core.common.measures import diffraction_limit

    limit = diffraction_limit(series.optics.na, series.optics.wavelength)["lateral"]
    lateral = v.layers["lateral FWHM (µm)"].data
    assert 0.95 * limit <= lateral.min() and lateral.max() <= 1.6 * limit, (limit, lateral)
    assert "lateral FWHM" in w.learn_result.value and " µm," in w.learn_result.value
    # deblur with the learnt model, twice: one layer
    w.iterations.value = 3
    for _ in range(2):
        w.deblur.clicked()
        wait_task(qtbot, w.deblur_task, timeout=60_000)
    out = [layer for layer in v.layers if layer.name.startswith(DEBLURRED_3D)]
    assert len(out) == 1 and out[0].data.shape == stack.shape
    # the time estimated before the iterations and the time taken, side by side
    assert "(estimated " in w.deblur_result.value and " s" in w.deblur_result.value
    from napari_psfspace.core.common.device import gpu_status

    on_gpu = gpu_status()[0]
    assert ("on the GPU" if on_gpu else "on the CPU") in w.deblur_result.value
    assert np.all(out[0].data >= 0) and tuple(out[0].scale) == (0.2, px, px)
    # where the stack lies, on its planes (napari's grid puts it beside), never blended
    raw = np.asarray(v.layers["bead stack"].extent.world)
    assert np.allclose(np.asarray(out[0].extent.world), raw)
    assert out[0].blending != "additive"
    # a re-learn keeps the deblurred stack; the step's button removes everything
    w.learn.clicked()
    wait_task(qtbot, w.learn_task, timeout=60_000)
    assert out[0] in v.layers
    # Cancel in every phase: within 2 s, nothing added. The iteration yields after each
    # wave of blocks (one a thread), the setup after each of its steps
    w.iterations.value = 10_000
    from napari_psfspace._layers import group_layers, remove_step

    assert remove_step(v, "3D") >= 2 and not group_layers(v, "3D")
    assert [layer.name for layer in v.layers] == ["bead stack", "a 2-D image"]
    for phase in ("setup", "iteration"):
        records = []
        w.deblur.clicked()
        w.deblur_task.worker.yielded.connect(records.append)
        if phase == "iteration":
            qtbot.waitUntil(lambda r=records: any(x.stage == "iteration" for x in r),
                            timeout=30_000)
            # one time estimate on the page: the progress line's, measured as it runs
            assert not w.deblur_result.value.startswith("estimate"), w.deblur_result.value
        w.deblur_task.request_cancel()
        wait_task(qtbot, w.deblur_task, timeout=2_000)
        assert w.deblur_result.value == "", phase  # no estimate of a run cancelled
        stages = {x.stage for x in records}
        assert ("iteration" in stages) == (phase == "iteration"), (phase, stages)
        assert w.deblur_task.status.value.startswith("cancelled"), phase
        assert not any(layer.name.startswith(DEBLURRED_3D) for layer in v.layers), phase
    if not on_gpu:  # a GPU asked for where there is none: one line, nothing added
        w.device.value = "gpu"
        w.deblur.clicked()
        wait_task(qtbot, w.deblur_task, timeout=30_000)
        assert w.deblur_task.status.value.startswith("failed"), w.deblur_task.status.value
        assert not any(layer.name.startswith(DEBLURRED_3D) for layer in v.layers)
        w.device.value = "auto"
    # a wrong model file is named, no traceback
    bad = tmp_path / "bad.npz"
    bad.write_text("not a model")
    w.model_file.value = bad
    w.deblur.clicked()
    assert "bad.npz" in w.deblur_task.status.value


def test_the_psf_grid_lies_on_the_stacks_planes():
    """Plane j of the shown grid is the kernel's plane K // 2 + j - plane: the bead
    plane on the stack's, zeros where the kernel has no plane, the stack's length."""
    from napari_psfspace._widgets._volume import on_stack_planes

    k, plane, n = 7, 1, 4
    volume = np.arange(k, dtype=np.float32)[:, None, None] * np.ones((k, 2, 3), np.float32)
    got = on_stack_planes(volume, plane, n)
    assert got.shape == (n, 2, 3)
    assert [float(p[0, 0]) for p in got] == [2.0, 3.0, 4.0, 5.0]  # K // 2 + j - plane
    # a stack deeper than the kernel: zeros beyond it
    got = on_stack_planes(volume, 5, 12)
    assert got[5, 0, 0] == 3.0 and not got[:2].any() and not got[9:].any()


def test_the_estimate_before_the_iterations_gives_way_to_the_measured_one():
    """The 3D page shows one time estimate: the one made before the iterations until they
    run, then none beside the progress line's (measured as they run)."""
    from napari_psfspace._widgets._volume import estimate_line
    from napari_psfspace.core.common.progress import Progress

    assert estimate_line(Progress("estimate", 0.0, "about 3.7 min")) == (
        "estimate: about 3.7 min")
    assert estimate_line(Progress("iteration", 0.1, "iteration 2 of 25, 3.1 min left "
                                                    "at most")) == ""
    assert estimate_line(Progress("setup", 0.0, "the acceleration's volumes")) is None


def test_an_ome_zarr_opened_lazily_is_learnt_and_deblurred(make_napari_viewer, qtbot,
                                                          bead_stack, tmp_path):
    """The plugin's reader opens an OME-Zarr as a dask layer scaled from its metadata;
    the 3D step learns from it and deblurs it (read in the worker), as from the same
    stack in memory."""
    pytest.importorskip("zarr", minversion="3")
    from napari_psfspace._widgets._volume import DEBLURRED_3D, stack_of
    from napari_psfspace.core.volume.deconvolve3d import STOP_FIT, richardson_lucy_3d
    from napari_psfspace.ome_zarr import create_ome_zarr

    stack, series = bead_stack
    px = series.optics.pixel_size
    arr = create_ome_zarr(tmp_path / "beads.zarr", stack.shape, dtype=stack.dtype,
                          voxel_size=(0.2, px, px), chunk=128)
    arr[:] = stack
    v = make_napari_viewer(show=True)
    v.window._qt_window.resize(1280, 800)
    _, w = v.window.add_plugin_dock_widget(PLUGIN, "7. 3D PSF and 3D deblur")
    [layer] = v.open(str(tmp_path / "beads.zarr"), plugin=PLUGIN)
    assert type(layer.data).__module__.startswith("dask")  # lazy, not read whole
    assert tuple(layer.scale) == pytest.approx((0.2, px, px))
    assert not isinstance(stack_of(layer)[0], np.ndarray)  # the worker reads it
    w.image.value = layer
    w.radius.set_calibration(w.radius.pixel_size, float(int(series.psf_radius.max())))
    w.learn.clicked()
    wait_task(qtbot, w.learn_task, timeout=60_000)
    assert w.operator is not None and w.operator.image_shape == stack.shape
    w.iterations.value = 3
    w.deblur.clicked()
    wait_task(qtbot, w.deblur_task, timeout=60_000)
    [out] = [x for x in v.layers if x.name.startswith(DEBLURRED_3D)]
    same = richardson_lucy_3d(stack, w.operator, n_iter=3,
                              stop=STOP_FIT if w.stop.value else None,
                              accelerate=bool(w.accelerate.value)).volume
    assert np.abs(np.asarray(out.data) - same).max() <= 1e-5 * same.max()
