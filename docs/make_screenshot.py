"""Screenshot of the plugin at work for the README: ``docs/images/plugin.png``.

Opens napari (a real window: canvas screenshots of hidden viewers come out black),
loads the sample data and clicks through the three dock widgets as a user would:
detect beads, review the patches and reject one, learn the operator and save it; the
model's maps are shown side by side with the image, as the panel shows them.
Without a display run it under a virtual X server::

    xvfb-run -a python docs/make_screenshot.py
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import napari
from qtpy.QtWidgets import QApplication

from napari_psfspace._sample_data import simulated_beads
from napari_psfspace._widgets import (
    LearnOperatorWidget,
    PickBeadsWidget,
    ReviewPatchesWidget,
)
from napari_psfspace._widgets._view import SideBySide

OUT = Path(__file__).resolve().parent / "images" / "plugin.png"


def wait(task, timeout: float = 120.0) -> None:
    """Process Qt events until the widget's job is done."""
    app = QApplication.instance()
    t0 = time.time()
    while task.running and time.time() - t0 < timeout:
        app.processEvents()
        time.sleep(0.02)
    app.processEvents()


def main(out: Path = OUT) -> Path:
    viewer = napari.Viewer(show=True, title="napari-psfspace")
    viewer.window.resize(1700, 1050)
    for data, kwargs, kind in simulated_beads():
        getattr(viewer, f"add_{kind}")(data, **kwargs)

    pick, review, learn = (PickBeadsWidget(viewer), ReviewPatchesWidget(viewer),
                           LearnOperatorWidget(viewer))
    learn.side_view = SideBySide(viewer)  # the model's maps beside the image, as the panel
    viewer.window.add_dock_widget(pick, name="1. Pick beads", area="right")
    viewer.window.add_dock_widget(review, name="2. Review patches", area="right",
                                  tabify=True)
    viewer.window.add_dock_widget(learn, name="3. Learn operator", area="right",
                                  tabify=True)

    pick.detect.clicked()
    wait(pick.task)
    review.extract.clicked()
    wait(review.task)
    flagged = [k for k in range(len(review.review)) if review.review.outlier[k]]
    review.patch.value = flagged[0] if flagged else 0
    review.reject.clicked()

    with tempfile.TemporaryDirectory() as tmp:
        learn.save_path.value = Path(tmp) / "psf_model.npz"
        learn.learn.clicked()
        wait(learn.task)
    learn.show_psf.clicked()
    QApplication.instance().processEvents()
    out.parent.mkdir(parents=True, exist_ok=True)
    viewer.screenshot(str(out), canvas_only=False)
    viewer.close()
    return out


if __name__ == "__main__":
    print(main(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT))
