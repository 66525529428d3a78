"""The front door: one dock, "PSF space", with a tab per step of the workflow.

Beads -> Review -> Model -> Diagnose -> Family -> Deblur, and 3D for z-stacks. Each tab
holds one of the step widgets (the same classes the Plugins menu offers one by one), in a
scroll area so that the dock fits a laptop screen (1280 x 800) with the canvas beside it
whatever the step shows. A tab is enabled once its input exists (an image; a beads layer
for Review; a learnt model or family for Deblur; a z-stack for 3D), and says why not in
its tooltip otherwise. The steps share their state through the viewer's layers (the beads
layer carries the user's rejections) and through the panel: the PSF radius set in Beads
is the radius of every later step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from napari.layers import Image, Points
from qtpy.QtCore import Qt
from qtpy.QtWidgets import QPushButton, QScrollArea, QTabWidget, QVBoxLayout, QWidget

from ._deblur import DeblurWidget
from ._diagnose import DiagnoseWidget
from ._layers import BEADS, OPERATOR_KEY, SUBSPACE_KEY, remove_step, step_layers
from ._learn_operator import LearnOperatorWidget
from ._learn_subspace import LearnSubspaceWidget
from ._pick_beads import PickBeadsWidget
from ._review_patches import ReviewPatchesWidget
from ._volume import Volume3DWidget

if TYPE_CHECKING:
    import napari

#: (tab title, widget class, what the step needs, in words for its tooltip).
STEPS = (
    ("Beads", PickBeadsWidget, "an image layer"),
    ("Review", ReviewPatchesWidget, "a beads layer (detect beads first)"),
    ("Model", LearnOperatorWidget, "an image layer"),
    ("Diagnose", DiagnoseWidget, "an image layer"),
    ("Family", LearnSubspaceWidget, "an image layer"),
    ("Deblur", DeblurWidget, "a learnt model or family (Model or Family step)"),
    ("3D", Volume3DWidget, "a z-stack image layer (Z, Y, X)"),
)
#: Widest the dock asks for (px): the canvas keeps the rest of a 1280 px screen.
PANEL_WIDTH = 380


def _has(viewer, test) -> bool:
    return any(test(layer) for layer in viewer.layers)


def _is_image(layer) -> bool:
    return isinstance(layer, Image)


def _is_beads(layer) -> bool:
    return isinstance(layer, Points) and (layer.name == BEADS or "status" in layer.features)


def _is_model(layer) -> bool:
    meta = layer.metadata or {}
    return OPERATOR_KEY in meta or SUBSPACE_KEY in meta


#: What enables each step (a test on the viewer's layers).
NEEDS = {
    "Beads": _is_image,
    "Review": _is_beads,
    "Model": _is_image,
    "Diagnose": _is_image,
    "Family": _is_image,
    "Deblur": _is_model,
    "3D": lambda layer: _is_image(layer) and layer.ndim == 3 and not layer.rgb,
}


class PsfSpacePanel(QWidget):
    """The workflow in one dock: a tab per step, enabled once its input exists.

    Parameters
    ----------
    viewer : napari.viewer.Viewer
        The viewer (napari passes a public-only proxy of it through the Plugins menu).

    Attributes
    ----------
    steps : dict of str to widget
        The step widgets by tab title ("Beads", "Review", "Model", "Diagnose",
        "Family", "Deblur", "3D").
    tabs : QTabWidget
    """

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        super().__init__()
        self._viewer = viewer
        self.tabs = QTabWidget()
        self.tabs.setElideMode(Qt.TextElideMode.ElideNone)  # titles always whole
        self.tabs.setUsesScrollButtons(True)
        self.tabs.setDocumentMode(True)
        self.steps: dict = {}
        self.clear_buttons: dict = {}
        for title, cls, _ in STEPS:
            widget = cls(viewer)
            self.steps[title] = widget
            scroll = QScrollArea()
            scroll.setWidgetResizable(True)
            scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
            scroll.setWidget(widget.native)
            page = QWidget()
            box = QVBoxLayout(page)
            box.setContentsMargins(0, 0, 0, 0)
            box.addWidget(scroll)
            clear = QPushButton(f"Remove the {title} step's layers")
            clear.setToolTip("Remove every layer this step made (results, titles, "
                             "colour bars); the data and the other steps' layers stay.")
            clear.clicked.connect(lambda _=False, t=title: self.clear_step(t))
            box.addWidget(clear)
            self.clear_buttons[title] = clear
            self.tabs.addTab(page, title)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.tabs)
        self.setMaximumWidth(PANEL_WIDTH + 40)
        self.setMinimumHeight(0)
        # one radius for every step: the one set in Beads
        self.steps["Beads"].radius.value_edit.changed.connect(self._share_radius)
        viewer.layers.events.inserted.connect(self.update_steps)
        viewer.layers.events.removed.connect(self.update_steps)
        viewer.layers.events.changed.connect(self.update_steps)
        self.update_steps()

    def sizeHint(self):  # noqa: N802 (Qt's name)
        hint = super().sizeHint()
        hint.setWidth(min(hint.width(), PANEL_WIDTH))
        hint.setHeight(min(hint.height(), 400))
        return hint

    def minimumSizeHint(self):  # noqa: N802 (Qt's name)
        hint = super().minimumSizeHint()
        hint.setHeight(min(hint.height(), 200))
        return hint

    def _share_radius(self, *_) -> None:
        source = self.steps["Beads"].radius
        for title in ("Review", "Model", "Diagnose", "Family"):
            edit = getattr(self.steps[title], "radius", None)
            if edit is not None and edit is not source:
                edit.set_calibration(edit.pixel_size, source.pixels)

    def clear_step(self, title: str) -> int:
        """Remove the layers the step ``title`` made (one group); how many went."""
        return remove_step(self._viewer, title)

    def enabled_steps(self) -> list[str]:
        """The titles of the tabs enabled now."""
        return [self.tabs.tabText(i) for i in range(self.tabs.count())
                if self.tabs.isTabEnabled(i)]

    def update_steps(self, *_) -> None:
        """Enable each step whose input exists; say in its tooltip what it needs."""
        for i, (title, _, need) in enumerate(STEPS):
            ok = _has(self._viewer, NEEDS[title])
            self.tabs.setTabEnabled(i, ok)
            self.tabs.setTabToolTip(i, "" if ok else f"{title} needs {need}.")
            self.clear_buttons[title].setEnabled(bool(step_layers(self._viewer, title)))
        if not self.tabs.isTabEnabled(self.tabs.currentIndex()):
            for i in range(self.tabs.count()):
                if self.tabs.isTabEnabled(i):
                    self.tabs.setCurrentIndex(i)
                    break


__all__ = ["STEPS", "PsfSpacePanel"]
