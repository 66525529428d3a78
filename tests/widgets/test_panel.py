"""The "PSF space" panel, opened as a user opens it: through the Plugins menu's door
(``viewer.window.add_plugin_dock_widget``, which hands widgets a public-only proxy of the
viewer), in a 1280 x 800 window."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import assert_maps_read_with_overlays, wait_task

PLUGIN = "napari-psfspace"


def _files(*folders):
    return {p for f in folders for p in f.rglob("*")}


@pytest.fixture
def laptop(make_napari_viewer, bead_image, tmp_path, monkeypatch):
    """(viewer, dock, panel, working directory): a shown viewer at 1280 x 800 holding
    the bead image, the panel docked through the Plugins menu's door, the working
    directory an empty folder."""
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    v = make_napari_viewer(show=True)
    v.window._qt_window.resize(1280, 800)  # not kept: a fixture holding the main window
    dock, panel = v.window.add_plugin_dock_widget(PLUGIN, "PSF space")
    image, truth = bead_image
    px = truth.optics.pixel_size
    v.add_image(image, name="beads image", scale=(px, px),
                metadata={"psf_radius": truth.psf_radius, "pixel_size_um": px})
    return v, dock, panel, cwd


def _canvas_size(v) -> tuple[int, int]:
    canvas = v.window._qt_viewer.canvas.native
    return canvas.width(), canvas.height()


def _settle(qtbot):
    qtbot.wait(50)


def test_the_panel_gets_the_proxy_and_fits_a_laptop_screen_with_the_canvas(laptop, qtbot):
    v, dock, panel, _ = laptop
    window = v.window._qt_window
    assert type(panel._viewer).__name__ == "PublicOnlyProxy"  # the user's door
    titles = [panel.tabs.tabText(i) for i in range(panel.tabs.count())]
    assert titles == ["Beads", "Review", "Model", "Diagnose", "Family", "Deblur", "3D"]
    # one 2-D image: no family to learn, so no Family tab
    assert panel.offered_steps() == ["Beads", "Review", "Model", "Diagnose", "Deblur", "3D"]
    for i in range(panel.tabs.count()):
        if not panel.tabs.isTabVisible(i):
            continue
        panel.tabs.setCurrentIndex(i)
        _settle(qtbot)
        # the window did not grow past the screen, and the canvas keeps most of it
        assert window.width() <= 1280 and window.height() <= 800, titles[i]
        size = _canvas_size(v)
        assert size[0] >= 400 and size[1] >= 500, (titles[i], size)
        # the whole dock lies inside the window: every control is on screen (a step
        # taller than the dock scrolls inside its tab)
        top_left = dock.mapTo(window, dock.rect().topLeft())
        assert top_left.x() >= 0 and top_left.y() >= 0
        assert top_left.x() + dock.width() <= window.width()
        assert top_left.y() + dock.height() <= window.height()
        # nothing cut on the right: the step is no wider than the room its tab has
        from qtpy.QtWidgets import QScrollArea

        scroll = panel.tabs.currentWidget().findChild(QScrollArea)
        assert scroll.widget().minimumSizeHint().width() <= scroll.viewport().width(), (
            titles[i])
        # and the dock cannot be dragged narrower than that content
        assert panel.minimumWidth() >= scroll.widget().minimumSizeHint().width(), titles[i]
        _assert_tabs_whole(panel)


def test_every_page_fits_the_dock_with_a_long_stack_name_open(laptop, qtbot):
    """A stack named as the SP8 file is ("sp8_series045_beads_zyx_uint8") widens no page:
    every step's page, the 3D page's included, fits the dock's width, and the dock is
    not widened past it."""
    from qtpy.QtWidgets import QScrollArea

    from napari_psfspace._widgets._panel import PANEL_WIDTH

    v, dock, panel, _ = laptop
    v.add_image(np.zeros((4, 64, 64), np.float32), name="sp8_series045_beads_zyx_uint8",
                scale=(0.3, 0.1, 0.1))
    _settle(qtbot)
    panel._fit_width()
    assert panel.minimumWidth() <= PANEL_WIDTH
    for i in range(panel.tabs.count()):
        if not panel.tabs.isTabVisible(i):
            continue
        panel.tabs.setCurrentIndex(i)
        _settle(qtbot)
        scroll = panel.tabs.currentWidget().findChild(QScrollArea)
        assert scroll.widget().minimumSizeHint().width() <= scroll.viewport().width(), (
            panel.tabs.tabText(i))
        assert dock.width() <= PANEL_WIDTH + 20, dock.width()  # the dock's frame at most


def _assert_tabs_whole(panel) -> None:
    """Every shown tab's label whole and inside the bar (no scroll buttons hiding one)."""
    bar = panel.tabs.tabBar()
    for i in range(panel.tabs.count()):
        if not panel.tabs.isTabVisible(i):
            continue
        rect, text = bar.tabRect(i), panel.tabs.tabText(i)
        assert rect.width() >= bar.fontMetrics().horizontalAdvance(text), text
        room = panel.tabs.width()
        assert rect.left() >= 0 and rect.right() < room, (text, rect, room)


def test_the_panel_opens_on_beads_and_says_what_each_step_needs(make_napari_viewer,
                                                                bead_image, qtbot):
    v = make_napari_viewer(show=True)
    v.window._qt_window.resize(1280, 800)
    _, panel = v.window.add_plugin_dock_widget(PLUGIN, "PSF space")
    qtbot.wait(100)  # laid out
    assert panel.tabs.tabText(panel.tabs.currentIndex()) == "Beads"
    assert "Family" not in panel.offered_steps()
    # nothing open: the page says what Beads needs, its controls greyed
    note = panel.needs["Beads"]
    assert note.isVisibleTo(panel) and "image" in note.text()
    assert not panel.steps["Beads"].native.isEnabled()
    _assert_tabs_whole(panel)
    image, truth = bead_image
    v.add_image(image, name="one")
    qtbot.wait(20)
    assert not note.isVisibleTo(panel) and panel.steps["Beads"].native.isEnabled()
    assert "Family" not in panel.offered_steps()  # one 2-D image is no family
    assert panel.needs["3D"].text().startswith("3D needs a z-stack")
    v.add_image(image * 1.1, name="two")
    qtbot.wait(50)
    assert "Family" in panel.offered_steps()
    _assert_tabs_whole(panel)  # all seven whole
    assert panel.steps["Family"].source.value == "image layers"  # no stack: the layers
    v.layers.remove("two")
    assert "Family" not in panel.offered_steps()
    v.add_image(np.stack([image, image]), name="stack")
    assert "Family" in panel.offered_steps() and "3D" in panel.ready_steps()


def test_the_radius_set_in_beads_is_every_later_steps_radius(laptop):
    v, dock, panel, _ = laptop
    beads = panel.steps["Beads"].radius
    beads.set_calibration(beads.pixel_size, 11.0)
    for title in ("Review", "Model", "Diagnose", "Family", "3D"):
        assert np.isclose(panel.steps[title].radius.pixels, 11.0, atol=0.01), title


def test_learning_writes_no_file_unless_asked(make_napari_viewer, bead_image, tmp_path,
                                              monkeypatch, qtbot):
    """A model learnt from an image read from a folder: nothing appears in that folder,
    nor in the working directory, unless the user names a file."""
    from napari_psfspace.io import write_tiff

    data = tmp_path / "data"
    data.mkdir()
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    image, truth = bead_image
    path = data / "beads.tif"
    write_tiff(path, image.astype(np.float32), pixel_size=truth.optics.pixel_size)
    v = make_napari_viewer()
    v.open(str(path), plugin=PLUGIN)
    before = _files(data, cwd)
    _, learn = v.window.add_plugin_dock_widget(PLUGIN, "3. Learn operator")
    learn.learn.clicked()
    wait_task(qtbot, learn.task, timeout=60_000)
    assert learn.operator is not None
    assert _files(data, cwd) == before
    target = tmp_path / "chosen" / "model.npz"
    target.parent.mkdir()
    learn.save_path.value = target
    learn.learn.clicked()
    wait_task(qtbot, learn.task, timeout=60_000)
    assert target.exists() and _files(data, cwd) == before


def _click_and_wait(qtbot, widget, button, timeout=120_000):
    button.clicked()
    wait_task(qtbot, widget.task, timeout=timeout)


def test_results_are_never_offered_as_images_to_work_on(laptop, qtbot):
    """After Beads and Review on one 2-D image, the viewer holds the bead gallery and
    colour bars as image layers: no step offers them as its input, and Family (which
    needs two images of one shape, or a stack) is not offered."""
    v, dock, panel, cwd = laptop
    steps = panel.steps
    image = v.layers["beads image"]
    steps["Beads"].image.value = image
    _click_and_wait(qtbot, steps["Beads"], steps["Beads"].detect)
    steps["Review"].image.value = image
    _click_and_wait(qtbot, steps["Review"], steps["Review"].extract)
    images = [layer for layer in v.layers if layer.__class__.__name__ == "Image"]
    assert len(images) >= 2  # the gallery at least, beside the data
    assert "Family" not in panel.offered_steps()
    for title in ("Beads", "Review", "Model", "Diagnose", "Deblur"):
        offered = [layer.name for layer in steps[title].image.choices]
        assert offered == ["beads image"], (title, offered)
    # a second image of another shape is no family either; one of the same shape is
    v.add_image(np.asarray(image.data)[:-8], name="cropped")
    assert "Family" not in panel.offered_steps()
    v.add_image(np.asarray(image.data) * 1.1, name="second")
    assert "Family" in panel.offered_steps()
    assert [layer.name for layer in steps["Family"].layers.choices] == [
        "beads image", "cropped", "second"]


def test_side_by_side_reads_at_the_panels_view_and_at_naparis_home(laptop, qtbot):
    """After Model, napari's grid shows the image and each of the step's maps in a cell
    of its own, named with its unit and with its colour bar; nothing else is shown. The
    overlays' settings (grid, camera, fonts, bar size) put no text over another or over
    the data, at the panel's view and after napari's Home (napari 0.9: the canvas size is
    in its model). Leaving the view gives the user's grid, scale bar and layers back."""
    from napari_psfspace._layers import OVERLAYS_KEY, group_layers
    from napari_psfspace._widgets._view import collisions, grid_of, scale_bar_of

    v, dock, panel, cwd = laptop
    grid, bar = grid_of(v), scale_bar_of(v)
    grid.spacing = 0.1  # the user's own settings, to be given back
    image = v.layers["beads image"]
    steps = panel.steps
    _click_and_wait(qtbot, steps["Beads"], steps["Beads"].detect)
    beads = [layer for layer in v.layers if layer.__class__.__name__ == "Points"]
    panel.tabs.setCurrentIndex(2)  # Model
    _click_and_wait(qtbot, steps["Model"], steps["Model"].learn)
    _settle(qtbot)
    maps = [layer for layer in group_layers(v, "Model")
            if OVERLAYS_KEY in (layer.metadata or {})]
    hidden = {m.name for m in maps if not m.visible}  # weight maps made hidden
    assert hidden and grid.enabled and grid.stride == 1 and bar.visible
    shown = [layer.name for layer in v.layers if layer.visible]
    assert set(shown) == {image.name} | {m.name for m in maps if m.visible}
    assert not any(layer.visible for layer in beads)  # marks on the image: not a cell
    assert image.name_overlay.visible  # the input is named too
    for layer in maps:
        overlay = getattr(layer, "colorbar", None) or layer.face_colorbar
        assert overlay.visible and layer.name_overlay.visible, layer.name
        assert layer.name.endswith(")"), layer.name
    # napari 0.9 and later keep the canvas size in the model: the check reads it
    live = getattr(getattr(v, "canvas", None), "size", None) is not None
    assert collisions(v) == []
    v.reset_view()  # napari's Home button
    _settle(qtbot)
    assert collisions(v) == []
    if live:  # the view's data fill their cells as far as the margins let them
        from napari_psfspace._widgets._view import MARGIN_LEFT, MARGIN_RIGHT

        rows, cols = grid.actual_shape(list(v.layers))
        cell_w = (v.canvas.size[1] - (cols - 1) * grid.spacing) / cols
        width = np.ptp(np.asarray(image.extent.world)[:, -1]) * v.scene.camera.zoom
        assert width >= 0.5 * (cell_w - MARGIN_LEFT - MARGIN_RIGHT)
    # Beads is clicked on the image: the user's grid back, the image and its beads, no
    # map over them; then the results again
    panel.tabs.setCurrentIndex(0)
    _settle(qtbot)
    assert not grid.enabled and grid.spacing == 0.1 and not bar.visible
    assert all(layer.visible for layer in beads) and not image.name_overlay.visible
    assert image.visible and not any(m.visible for m in maps)
    panel.tabs.setCurrentIndex(2)
    _settle(qtbot)
    assert grid.enabled
    # closing the panel gives the user's view back; opening it, the step's view again
    dock.hide()
    _settle(qtbot)
    assert not grid.enabled and grid.spacing == 0.1 and image.visible
    dock.show()
    _settle(qtbot)
    assert grid.enabled
    panel.side_by_side.setChecked(False)
    _settle(qtbot)
    assert not grid.enabled and grid.spacing == 0.1 and not bar.visible
    assert all(layer.visible for layer in v.layers if layer.name not in hidden)
    # outside the grid the maps lie on each other: only the selected one is named
    named = [m.name for m in maps if m.name_overlay.visible]
    assert named == [v.layers.selection.active.name]


def test_every_step_twice_the_same_layers_and_cancel(laptop, qtbot,
                                                                       monkeypatch):
    """The walk a user takes, each step run twice: the same layer names after each
    run, the user's rejection honoured by Diagnose, Cancel honoured at every step (in
    every phase, even a core step that cannot yield: tests/widgets/test_worker.py), and
    no file anywhere (none was asked for)."""
    from functools import partial

    import napari_psfspace._widgets._diagnose as diagnose_module
    # the diagnosis's baseline and final model only (no effect tried): its layers, inputs
    # and Cancel are what is tested here (the loop itself: tests/test_diagnose.py)
    monkeypatch.setattr(diagnose_module, "iter_diagnose",
                        partial(diagnose_module.iter_diagnose, max_steps=0))
    v, dock, panel, cwd = laptop
    image = v.layers["beads image"]
    v.add_image(np.asarray(image.data) * 1.1, name="beads image 2", scale=image.scale,
                metadata=dict(image.metadata))
    steps = panel.steps
    assert panel.ready_steps() == ["Beads", "Model", "Diagnose", "Family"]
    steps["Beads"].image.value = image
    buttons = {"Beads": "detect", "Review": "extract", "Model": "learn",
               "Diagnose": "diagnose", "Family": "learn", "Deblur": "run_button"}
    family = steps["Family"]
    family.source.value = "image layers"
    family.layers.value = [image, v.layers["beads image 2"]]
    steps["Deblur"].max_iter.value = 40  # the layers, not the convergence, are tested
    for title, attr in buttons.items():
        widget = steps[title]
        if hasattr(widget, "image"):
            widget.image.value = image
        if title == "Diagnose":  # a bead rejected by hand stays out of the diagnosis
            pts = v.layers["beads"]
            kept = np.flatnonzero(np.asarray(pts.features["status"]) == "kept")
            from napari_psfspace._layers import set_statuses
            rejected_id = int(pts.features["id"].iloc[kept[0]])
            set_statuses(pts, [rejected_id], ["rejected"])
        names = statuses = None
        for _ in range(2):  # a re-run updates its layers: the second shows any pile-up
            _click_and_wait(qtbot, widget, getattr(widget, attr))
            assert "failed" not in widget.task.status.value, (title, widget.task.status.value)
            now = [layer.name for layer in v.layers]
            assert names is None or now == names, (title, names, now)
            names = now
            if title == "Model":  # the user's beads, not the last run's verdicts, each time
                got = list(v.layers["beads"].features["status"])
                assert statuses is None or got == statuses
                statuses = got
        assert not any(n.endswith("]") for n in names), names  # no "name [1]" copies
        if title == "Beads":
            assert "Review" in panel.ready_steps()
            assert "Deblur" not in panel.ready_steps()
        if title == "Model":  # the model just learnt is Deblur's operator
            assert "Deblur" in panel.ready_steps()
            assert steps["Deblur"].source.value == "from the viewer"
            assert steps["Deblur"].model() is widget.operator
        if title == "Diagnose":
            d = widget.diagnosis
            # the model Diagnose refined is Deblur's operator now
            assert steps["Deblur"].model() is d.operator
            row = np.flatnonzero(np.hypot(*(d.context.beads.positions
                                            - pts.data[kept[0]]).T) < 1.0)
            assert len(row) == 1 and d.context.beads.status[row[0]] == "rejected"
        # Cancel: the job ends and nothing is added
        getattr(widget, attr).clicked()
        assert widget.task.running, title
        widget.task.cancel.clicked()
        wait_task(qtbot, widget.task, timeout=10_000)
        assert widget.task.status.value.startswith("cancelled"), title
        assert [layer.name for layer in v.layers] == names, title
    assert _files(cwd) == set()
    _check_words(v, panel)  # before the groups' buttons remove every result
    _check_groups(v, panel, list(buttons))


#: Symbols of the paper and the statistics that a microscopist is not shown: they go to
#: tooltips and the docs.
JARGON = r"\bh_i\b|\bh_\d|alpha_i|\ba_j\b|\ba_\d|chi2|\bdof\b|Biggs|Gamma|\b[IJ] = |^[IJ] \("


def _check_words(v, panel):
    """No layer name and no text the panel shows (labels, buttons, choices, table
    headers and cells, result texts) uses the paper's symbols or "chi2/dof"."""
    import re

    from qtpy.QtWidgets import (
        QAbstractButton,
        QComboBox,
        QLabel,
        QLineEdit,
        QTableWidget,
        QTextEdit,
    )

    texts = [layer.name for layer in v.layers]
    texts += [line for w in panel.findChildren(QTextEdit)
              for line in w.toPlainText().splitlines()]
    for w in panel.findChildren(QLabel) + panel.findChildren(QAbstractButton):
        texts.append(w.text())
    texts += [w.text() for w in panel.findChildren(QLineEdit)]
    for w in panel.findChildren(QComboBox):
        texts += [w.itemText(i) for i in range(w.count())]
    for t in panel.findChildren(QTableWidget):
        texts += [t.horizontalHeaderItem(j).text() for j in range(t.columnCount())
                  if t.horizontalHeaderItem(j) is not None]
        texts += [t.item(i, j).text() for i in range(t.rowCount())
                  for j in range(t.columnCount()) if t.item(i, j) is not None]
    found = sorted({t for t in texts if re.search(JARGON, t)})
    assert not found, found


def _check_groups(v, panel, titles):
    """Each step's layers are one group: each map named with its unit and shown with
    napari's name and colour bar, and removed together by the step's button, the other
    steps' layers and the data left alone."""
    from napari_psfspace._layers import STEP_KEY, step_layers

    groups = {t: {layer.name for layer in step_layers(v, t)} for t in titles}
    assert all(groups.values()), groups
    made = set().union(*groups.values())
    assert {layer.name for layer in v.layers} - made == {"beads image", "beads image 2"}
    assert_maps_read_with_overlays(v, made)
    for t in reversed(titles):
        before = {layer.name for layer in v.layers}
        assert panel.clear_buttons[t].isEnabled(), t
        panel.clear_buttons[t].click()
        assert before - {layer.name for layer in v.layers} == groups[t], t
        assert not panel.clear_buttons[t].isEnabled(), t
        assert not any((layer.metadata or {}).get(STEP_KEY) == t for layer in v.layers)
    assert {layer.name for layer in v.layers} == {"beads image", "beads image 2"}
