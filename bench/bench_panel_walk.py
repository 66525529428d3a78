"""A scripted walk through the "PSF space" panel on the sample, as a user takes it.

    xvfb-run -a -s "-screen 0 1280x800x24" python bench/bench_panel_walk.py [--out docs/images]

Opens napari at 1280 x 800 (a real window: screenshots of hidden viewers come out black),
docks the panel through the Plugins menu's door (``add_plugin_dock_widget``, which hands
it a public-only proxy of the viewer), opens the sample and clicks through the steps:
Beads (detect), Review (extract the patches), Model (learn), Diagnose, Deblur (the model
Diagnose refined), then Family and 3D on the second sample, the focus series.
Each step's seconds and the canvas left to the image are printed as a table; a
screenshot of the window after each step goes to ``--out`` (``panel_<step>.png``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import napari
from qtpy.QtWidgets import QApplication

from benchlib import table, wait_for
from napari_psfspace._sample_data import simulated_beads, simulated_focus_series

OUT = Path(__file__).resolve().parents[1] / "docs" / "images"


def _open_focus_series(viewer):
    """The focus-series sample (File > Open Sample): a z-stack, so several images."""
    stack, kwargs, _ = simulated_focus_series()[0]
    return viewer.add_image(stack, **kwargs)


def _family(widget) -> None:
    """The Family step on the focus-series sample, every slice."""
    widget.source.value = "slices of a stack layer"
    widget.stack.value = widget._viewer.layers["simulated focus series"]
    widget.learn.clicked()


def _volume(widget) -> None:
    """The 3D step on the focus-series sample: learn its 3D PSF."""
    widget.image.value = widget._viewer.layers["simulated focus series"]
    widget.learn.clicked()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    viewer = napari.Viewer(show=True, title="napari-psfspace")
    window = viewer.window._qt_window
    window.resize(1280, 800)
    app = QApplication.instance()
    _, panel = viewer.window.add_plugin_dock_widget("napari-psfspace", "PSF space")
    image, kwargs, _ = simulated_beads()[0]
    viewer.add_image(image, **kwargs)
    app.processEvents()
    steps = [
        ("Beads", lambda w: w.detect.clicked()),
        ("Review", lambda w: w.extract.clicked()),
        ("Model", lambda w: w.learn.clicked()),
        ("Diagnose", lambda w: w.diagnose.clicked()),
        ("Deblur", lambda w: w.run_button.clicked()),
        ("Family", _family),
        ("3D", _volume),
    ]
    rows = []
    total = 0.0
    for title, click in steps:
        widget = panel.steps[title]
        if title == "Family":  # offered once there are several images
            stack = _open_focus_series(viewer)
            viewer.dims.set_point(0, stack.translate[0] + 2 * stack.scale[0])
        panel.tabs.setCurrentIndex(list(panel.steps).index(title))
        app.processEvents()
        task = getattr(widget, "task", None) or widget.learn_task
        t0 = time.perf_counter()
        click(widget)
        wait_for(task, 300.0)
        app.processEvents()
        seconds = time.perf_counter() - t0
        total += seconds
        canvas = viewer.window._qt_viewer.canvas.native
        path = args.out / f"panel_{title.lower()}.png"
        window.grab().save(str(path))
        rows.append({"step": title, "seconds": seconds,
                     "canvas": f"{canvas.width()}x{canvas.height()}",
                     "window": f"{window.width()}x{window.height()}",
                     "status": task.status.value[:60].replace("\n", " ")})
        print(rows[-1], flush=True)
    rows.append({"step": "all", "seconds": total, "canvas": "", "window": "", "status": ""})
    print(table(rows, [("step", "s"), ("seconds", ".1f"), ("canvas", "s"), ("window", "s"),
                       ("status", "s")]))
    viewer.close()


if __name__ == "__main__":
    main()
