"""The 3D step (``_widgets/_volume``), opened as a user opens it: through the Plugins
menu's door at 1280 x 800, on a simulated bead z-stack with a voxel size."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import wait_task

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
    w.radius.value = int(series.psf_radius.max())
    names = None
    for _ in range(2):
        w.learn.clicked()
        wait_task(qtbot, w.learn_task, timeout=60_000)
        now = [layer.name for layer in v.layers]
        assert names is None or now == names  # a re-run updates, never piles up
        names = now
    grid = v.layers[PSF_GRID_3D]
    op = grid.metadata[OPERATOR_3D_KEY]
    assert op is w.operator and grid.data.ndim == 3
    assert grid.data.shape[0] == op.kernel_shape[0]
    # the grid's bead plane on the stack's: world z of kernel plane K // 2 = op.plane
    assert grid.translate[0] + (op.kernel_shape[0] // 2) * grid.scale[0] == \
        pytest.approx(op.plane * 0.2)
    assert PSF_SECTIONS in v.layers and PSF_SECTIONS_Y in v.layers
    # the maps in nm (the stack is calibrated), their unit in their names
    assert all(f"{label} (nm)" in v.layers for _, label, _ in MAPS)
    assert np.isfinite(v.layers[f"{MAPS[0][1]} (nm)"].data).all()
    # the lateral FWHM where the optics put it: 1 to 1.6x the Airy disk's (the grid's
    # PSFs carry the field's aberrations; a map in px would read 3-6 here)
    from napari_psfspace.core.common.measures import diffraction_limit

    limit = 1000 * diffraction_limit(series.optics.na, series.optics.wavelength)["lateral"]
    lateral = v.layers["lateral FWHM (nm)"].data
    assert 0.95 * limit <= lateral.min() and lateral.max() <= 1.6 * limit, (limit, lateral)
    assert "lateral FWHM" in w.learn_result.value and " nm," in w.learn_result.value
    # deblur with the learnt model, twice: one layer
    w.iterations.value = 3
    for _ in range(2):
        w.deblur.clicked()
        wait_task(qtbot, w.deblur_task, timeout=60_000)
    out = [layer for layer in v.layers if layer.name.startswith(DEBLURRED_3D)]
    assert len(out) == 1 and out[0].data.shape == stack.shape
    assert np.all(out[0].data >= 0) and tuple(out[0].scale) == (0.2, px, px)
    # Cancel within a second, nothing added
    w.iterations.value = 10_000
    v.layers.remove(out[0])
    w.deblur.clicked()
    qtbot.waitUntil(lambda: w.deblur_task.running, timeout=5_000)
    qtbot.wait(200)
    w.deblur_task.request_cancel()
    wait_task(qtbot, w.deblur_task, timeout=1_000 + 5_000)
    assert DEBLURRED_3D not in v.layers
    # a wrong model file is named, no traceback
    bad = tmp_path / "bad.npz"
    bad.write_text("not a model")
    w.model_file.value = bad
    w.deblur.clicked()
    assert "bad.npz" in w.deblur_task.status.value
