"""Widget tests: napari viewer + pytest-qt; skipped where the GUI stack is absent.

The core suite runs in a minimal environment (no napari); these tests need
``pip install -e ".[testing]"`` (napari[pyqt6], pytest-qt, pytest-xvfb) and a display
(pytest-xvfb starts a virtual one).
"""

from __future__ import annotations

import importlib.util
import os
import shutil

import numpy as np
import pytest

_MISSING = [m for m in ("napari", "pytestqt", "qtpy") if importlib.util.find_spec(m) is None]
if _MISSING:
    pytest.skip(f"napari widget tests need {', '.join(_MISSING)} (pip install -e "
                "'.[testing]'); skipping tests/widgets", allow_module_level=True)
if not os.environ.get("DISPLAY") and shutil.which("Xvfb") is None:
    pytest.skip("napari widget tests need a display: no $DISPLAY and no Xvfb (Debian: "
                "apt-get install xvfb xauth, as .ci/run does); skipping tests/widgets",
                allow_module_level=True)


@pytest.fixture
def make_napari_viewer(make_napari_viewer):
    """napari's fixture, with every object alive once a viewer is made (the session's
    modules, the viewer's own Qt and vispy objects) kept out of the garbage collector's
    sight until the test ends (:func:`gc.freeze`): napari runs a full collection each time
    a layer is removed, which otherwise walks all of them again (a six-step walk removes
    about fifty layers)."""
    import gc

    def make(*args, **kwargs):
        viewer = make_napari_viewer(*args, **kwargs)
        gc.freeze()
        return viewer

    yield make
    gc.unfreeze()  # before napari's own teardown closes the viewers


@pytest.fixture(scope="session")
def bead_image():
    """A small simulated bead field (384 x 384, 25 beads) with its truth."""
    from napari_psfspace.core.simulation import simulate_beads

    image, truth = simulate_beads((384, 384), 25, seed=3)
    return image, truth


def calibrated_viewer(make_napari_viewer, image, truth, name: str):
    """A viewer holding a simulated image with its pixel size (scale) and PSF radius."""
    v = make_napari_viewer()
    px = truth.optics.pixel_size
    v.add_image(image, name=name, scale=(px, px),
                metadata={"psf_radius": truth.psf_radius, "pixel_size_um": px})
    return v


@pytest.fixture
def viewer(make_napari_viewer, bead_image):
    """A viewer holding the bead image with a 0.065 µm pixel (scale) and its PSF radius."""
    return calibrated_viewer(make_napari_viewer, *bead_image, "beads image")


def assert_maps_read_with_overlays(v, made) -> None:
    """Every image layer a step made is a map napari dresses: its name gives its unit in
    brackets, its name and colour-bar overlays are on, its colour bar's limits are the
    map's own (napari draws them from the layer); no layer is a colour bar or a title
    drawn as data."""
    from napari_psfspace._layers import OVERLAYS_KEY

    for name in made:
        layer = v.layers[name]
        assert not name.startswith(("colour bar", "titles")), name
        kind = layer.__class__.__name__
        if kind == "Points":  # no texts drawn as data: titles, colour-bar ticks
            assert not {"title", "tick"} & set(layer.features.columns), name
        if kind != "Image":
            continue
        assert OVERLAYS_KEY in layer.metadata, name
        assert name.endswith(")") and " (" in name, name
        assert layer.colorbar.visible and layer.name_overlay.visible, name


def wait_task(qtbot, task, timeout: int = 30_000) -> None:
    """Wait until a CoreTask's worker has finished."""
    qtbot.waitUntil(lambda: not task.running, timeout=timeout)


@pytest.fixture
def noise_image():
    return np.random.default_rng(0).normal(100, 5, (256, 256)).astype(np.float32)
