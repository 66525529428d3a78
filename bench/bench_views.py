"""Screenshots of the side-by-side view, as a user sees it, and what overlaps in them.

    xvfb-run -a -s "-screen 0 1280x800x24" python bench/run.py views [--out docs/images]

Opens napari at 1280 x 800, docks the "PSF space" panel through the Plugins menu's door
(``add_plugin_dock_widget``) and runs the steps on four data sets: the simulated sample
(Model, Diagnose, Deblur), a slice of the SP8 confocal stack (Model, Deblur), the SP8
stack (3D) and the simulated focus series (Family); the SP8 sets are read from
``../shared/data`` and left out where it is absent. After each step it takes the window
at the view the panel sets (``fit``), at twice its zoom (``zoom2``), at half of it and
after napari's Home button (``half``, ``home``: only counted), and prints what napari's
settings say overlaps in each (``_view.collisions``): a table, and
``view_<set>_<step>_<view>.png`` in ``--out``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import napari
import numpy as np
from qtpy.QtWidgets import QApplication

from benchlib import table, wait_for
from napari_psfspace._reader import read_tiff
from napari_psfspace._sample_data import simulated_beads, simulated_focus_series
from napari_psfspace._widgets._view import collisions
from napari_psfspace.io import read_image

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "images"
SP8 = ROOT.parent / "shared" / "data" / "sp8_confocal_beads" / "sp8_series045_beads_zyx_uint8.tif"
SP8_SLICE = 32


def settle() -> None:
    app = QApplication.instance()
    for _ in range(10):
        app.processEvents()
        time.sleep(0.02)


def run_step(panel, title: str, prepare=None) -> float:
    """Open the step's page, click its button, wait; the seconds it took."""
    widget = panel.steps[title]
    panel.tabs.setCurrentIndex(list(panel.steps).index(title))
    settle()
    if prepare is not None:
        prepare(widget)
    task = getattr(widget, "task", None) or widget.learn_task
    button = {"Beads": "detect", "Review": "extract", "Model": "learn",
              "Diagnose": "diagnose", "Deblur": "run_button", "Family": "learn",
              "3D": "learn"}[title]
    t0 = time.perf_counter()
    getattr(widget, button).clicked()
    wait_for(task)
    return time.perf_counter() - t0


def shoot(viewer, panel, name: str, step: str, out: Path, rows: list) -> None:
    """The window at the panel's view, at twice and half its zoom, and after napari's
    Home."""
    window = viewer.window._qt_window
    panel.view.fit()
    settle()
    zoom = viewer.scene.camera.zoom
    for view in ("fit", "zoom2", "half", "home"):
        if view in ("zoom2", "half"):
            viewer.scene.camera.zoom = zoom * (2.0 if view == "zoom2" else 0.5)
        elif view == "home":
            viewer.reset_view()
        settle()
        found = collisions(viewer)
        if view in ("fit", "zoom2"):
            window.grab().save(str(out / f"view_{name}_{step.lower()}_{view}.png"))
        rows.append({"set": name, "step": step, "view": view,
                     "cells": int(np.prod(viewer.canvas.grid.actual_shape(
                         list(viewer.layers)))),
                     "overlaps": len(found), "first": (found[0] if found else "")[:60]})
        print(rows[-1], file=sys.stderr, flush=True)
    panel.view.fit()
    settle()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list = []

    def viewer_with_panel():
        viewer = napari.Viewer(show=True, title="napari-psfspace")
        viewer.window._qt_window.resize(1280, 800)
        _, panel = viewer.window.add_plugin_dock_widget("napari-psfspace", "PSF space")
        settle()
        return viewer, panel

    # the sample: Model, Diagnose, Deblur
    viewer, panel = viewer_with_panel()
    image, kwargs, _ = simulated_beads()[0]
    viewer.add_image(image, **kwargs)
    for step in ("Beads", "Review", "Model", "Diagnose", "Deblur"):
        run_step(panel, step)
        if step in ("Model", "Diagnose", "Deblur"):
            shoot(viewer, panel, "sample", step, args.out, rows)
    viewer.close()

    # the focus series: Family
    viewer, panel = viewer_with_panel()
    stack, kwargs, _ = simulated_focus_series()[0]
    viewer.add_image(stack, **kwargs)

    def family(widget):
        widget.source.value = "slices of a stack layer"
        widget.stack.value = viewer.layers["simulated focus series"]

    run_step(panel, "Family", family)
    shoot(viewer, panel, "focus", "Family", args.out, rows)
    viewer.close()

    if SP8.exists():
        # a slice of the SP8 stack: Model, Deblur
        viewer, panel = viewer_with_panel()
        plane, info = read_image(SP8, index=SP8_SLICE)
        px = info.pixel_size
        viewer.add_image(plane, name=f"SP8 slice {SP8_SLICE}", scale=(px, px),
                         units=("µm", "µm"), metadata={"pixel_size_um": px})
        for step in ("Beads", "Model", "Deblur"):
            run_step(panel, step)
            if step != "Beads":
                shoot(viewer, panel, "sp8slice", step, args.out, rows)
        viewer.close()
        # the SP8 stack: 3D
        viewer, panel = viewer_with_panel()
        data, kwargs, _ = read_tiff(str(SP8))[0]
        viewer.add_image(data, **kwargs)
        run_step(panel, "3D")
        shoot(viewer, panel, "sp8stack", "3D", args.out, rows)
        viewer.close()
    else:
        print(f"{SP8} is absent: the SP8 sets are left out")

    print(table(rows, [("set", "s"), ("step", "s"), ("view", "s"), ("cells", "d"),
                       ("overlaps", "d"), ("first", "s")]))


if __name__ == "__main__":
    main()
