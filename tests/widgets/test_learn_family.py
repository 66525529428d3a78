"""Learn family: a stack's slices, 2-D layers and a folder; what is shown; saving;
cancel; bad choices."""

import numpy as np
import pytest

from conftest import wait_task
from napari_psfspace._layers import (
    SUB_BASIS,
    SUB_GRID,
    SUB_SPACE,
    SUBSPACE_KEY,
)
from napari_psfspace._widgets._learn_family import SOURCES, LearnFamilyWidget
from napari_psfspace.core.family import OperatorFamily, estimate_family
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.stacks import simulate_stack


@pytest.fixture(scope="module")
def stack():
    """Six 256 x 256 images of one microscope under hidden conditions, 12 beads each."""
    images, truths, _ = simulate_stack(6, (256, 256), 12, seed=5)
    return np.stack(images), truths


def test_stack_slices_learn_show_and_save(make_napari_viewer, qtbot, stack, tmp_path):
    data, truths = stack
    v = make_napari_viewer()
    r = float(np.median([t.psf_radius for t in truths]))
    v.add_image(data, name="z-stack", metadata={"psf_radius": r})
    w = LearnFamilyWidget(v)
    assert w.stack.value is v.layers["z-stack"]
    assert (w.first.value, w.last.value) == (0, 5)
    w.first.value, w.last.value = 1, 5  # five of the six slices
    path = tmp_path / "family.npz"
    w.save_path.value = path
    w.learn.clicked()
    wait_task(qtbot, w.task, timeout=120_000)

    sub = w.subspace
    assert sub is not None and sub.n_images == 5
    assert sub.metadata["labels"] == [f"z-stack[{z}]" for z in range(1, 6)]
    # the same family as the API on the same slices (same radius, held-out split)
    ref = estimate_family(list(data[1:6]), psf_radius=w.radius.pixels)
    assert np.allclose(sub.gammas, ref.gammas, atol=1e-8)
    # shown: a PSF grid per image (slider), the basis, the spatial maps
    grid = v.layers[SUB_GRID]
    assert grid.data.shape[0] == 5 and grid.metadata[SUBSPACE_KEY] is sub
    # the z slider shows each slice with its own PSF grid (the family starts at slice 1)
    assert grid.translate[0] == 1.0 and grid.scale[0] == 1.0
    # h_i and a_j as 2-D mosaics (the slider is the stack's alone)
    assert v.layers[SUB_BASIS].data.ndim == 2 and v.layers[SUB_SPACE].data.ndim == 2
    p = sub.basis.shape[-1]
    first = sub.basis[0] / np.abs(sub.basis[0]).max()
    assert np.allclose(v.layers[SUB_BASIS].data[:p, :p], first, atol=1e-6)
    # each on the stack's field (napari's grid puts them side by side)
    field = np.asarray(v.layers["z-stack"].extent.world)[:, -2:]
    for name in (SUB_SPACE, SUB_GRID, SUB_BASIS):
        box = np.asarray(v.layers[name].extent.world)[:, -2:]
        assert np.all(box[0] >= field[0] - 1) and np.all(box[1] <= field[1] + 1), name
    # the conditions: a table in the dock, a row an image, its place in the family
    table = w.conditions.value
    assert not w.conditions.native.isHidden() and len(table["data"]) == 5
    labels = [lab.rsplit("[", 1)[-1].rstrip("]") for lab in sub.metadata["labels"]]
    assert [row[0] for row in table["data"]] == labels
    coords = sub.condition_coordinates(2)
    assert [float(row[1]) for row in table["data"]] == pytest.approx(coords[:, 0], abs=0.006)
    # each grid tile is that image's operator (first tile: row 0, column 0)
    ys, xs, psfs = sub.psf_grids(6, images=[3])
    assert np.allclose(psfs[0, 0, 0], sub.psf_at(3, ys[0], xs[0]))
    # the family is a good model of slice 3 (the truth of image 3 of the stack)
    assert np.mean(grid_errors(sub.operator(2), truths[3], n=3)) < 0.15  # measured 0.064
    assert "held-out beads" in w.result.value and str(path) in w.result.value
    loaded = OperatorFamily.load(path)
    assert np.allclose(loaded.gammas, sub.gammas)


def test_image_layers_and_folder(make_napari_viewer, qtbot, stack, tmp_path):
    import tifffile

    data, truths = stack
    v = make_napari_viewer()
    for k in range(3):
        v.add_image(data[k], name=f"condition {k}")
    w = LearnFamilyWidget(v)
    w.radius.set_calibration(None, float(np.median([t.psf_radius for t in truths])))
    w.source.value = SOURCES[1]
    assert not w.layers.native.isHidden() and w.stack.native.isHidden()
    w.layers.value = [v.layers["condition 0"], v.layers["condition 2"]]
    w.holdout.value = False
    w.learn.clicked()
    wait_task(qtbot, w.task, timeout=120_000)
    assert w.subspace.n_images == 2
    assert w.subspace.metadata["labels"] == ["condition 0", "condition 2"]

    folder = tmp_path / "beads"
    folder.mkdir()
    for k in range(3):
        tifffile.imwrite(folder / f"img{k}.tif", data[k])
    w.source.value = SOURCES[2]
    w.folder.value = folder
    w.learn.clicked()
    wait_task(qtbot, w.task, timeout=120_000)
    assert w.subspace.n_images == 3
    assert v.layers[SUB_GRID].data.shape[0] == 3


def test_bad_choices_are_named(make_napari_viewer, qtbot, stack, tmp_path, monkeypatch):
    import napari_psfspace._widgets._learn_family as mod
    import napari_psfspace._widgets._worker as worker_mod

    shown = []
    monkeypatch.setattr(mod, "show_error", shown.append)
    monkeypatch.setattr(worker_mod, "show_error", shown.append)
    data, _ = stack
    v = make_napari_viewer()
    v.add_image(data, name="z-stack")
    w = LearnFamilyWidget(v)
    w.first.value = w.last.value = 2
    w.learn.clicked()
    assert not w.task.running and "last slice" in shown[-1]
    w.source.value = SOURCES[1]
    w.learn.clicked()
    assert "image layers" in shown[-1]
    w.source.value = SOURCES[2]
    w.folder.value = tmp_path  # empty
    w.learn.clicked()
    assert "holds no .tif" in shown[-1]
    # a stack of noise: no image has a bead (a core error, shown, nothing added)
    v.add_image(np.random.default_rng(0).normal(100, 3, (4, 128, 128)), name="noise")
    w.source.value = SOURCES[0]
    w.stack.value = v.layers["noise"]
    w.radius.set_calibration(None, 4.0)
    n = len(v.layers)
    w.learn.clicked()
    wait_task(qtbot, w.task)
    assert "at least 2 images with usable beads" in shown[-1]
    assert len(v.layers) == n and w.subspace is None


def test_cancel_adds_nothing(make_napari_viewer, qtbot, stack, tmp_path):
    data, truths = stack
    v = make_napari_viewer()
    v.add_image(data, name="z-stack",
                metadata={"psf_radius": float(np.median([t.psf_radius for t in truths]))})
    w = LearnFamilyWidget(v)
    path = tmp_path / "family.npz"
    w.save_path.value = path
    n = len(v.layers)
    w.learn.clicked()
    assert w.task.running and not w.learn.enabled
    with qtbot.waitSignal(w.task.worker.aborted, timeout=60_000):
        w.task.cancel.clicked()
    wait_task(qtbot, w.task)
    assert len(v.layers) == n and not path.exists() and w.subspace is None
    assert "cancelled" in w.task.status.value and w.learn.enabled


def test_a_stacks_conditions_are_named_by_their_focus_in_micrometres(make_napari_viewer):
    """The conditions of a family learnt from a stack are named by each slice's focus
    (µm) where the stack carries it (the focus series), by its z position (µm) where the
    stack is calibrated, and by the slice's index only where it is neither."""
    v = make_napari_viewer()
    data = np.zeros((4, 32, 32), np.float32)
    v.add_image(data, name="series", scale=(0.2, 0.1, 0.1),
                metadata={"z_um": [-0.6, -0.2, 0.2, 0.6]})
    v.add_image(data, name="calibrated", scale=(0.25, 0.1, 0.1), translate=(1.0, 0, 0))
    v.add_image(data, name="plain")
    w = LearnFamilyWidget(v)
    expected = {"series": ["-0.60 µm", "-0.20 µm", "+0.20 µm", "+0.60 µm"],
                "calibrated": ["z 1.00 µm", "z 1.25 µm", "z 1.50 µm", "z 1.75 µm"],
                "plain": ["0", "1", "2", "3"]}
    for name, want in expected.items():
        w.stack.value = v.layers[name]
        w.first.value, w.last.value = 0, 3
        _, _, labels, _ = w._inputs()
        assert labels == [f"{name}[{x}]" for x in want], name
