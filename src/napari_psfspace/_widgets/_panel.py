"""The front door: one dock, "PSF space", with a tab per step of the workflow.

Beads -> Review -> Model -> Diagnose -> Family -> Deblur, and 3D for z-stacks. Each tab
holds one of the step widgets (the same classes the Plugins menu offers one by one), in a
scroll area so that the dock fits a laptop screen (1280 x 800) with the canvas beside it
whatever the step shows. The panel opens on Beads. A step's controls are live once its
input exists (an image; a beads layer for Review; several images for Family, whose tab
shows only then; a learnt model or family for Deblur; a z-stack for 3D); until then its
page says, above the greyed controls, what it needs. The steps share their state
through the viewer's layers (the beads layer carries the user's rejections) and through
the panel: the PSF radius set in Beads is the radius of every later step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from napari.layers import Points
from qtpy.QtCore import Qt, QTimer
from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QLabel,
    QPushButton,
    QScrollArea,
    QStyle,
    QTabWidget,
    QVBoxLayout,
    QWidget,
)

from .._layers import (
    BEADS,
    OPERATOR_KEY,
    SUBSPACE_KEY,
    group_layers,
    input_images,
    is_input_image,
    remove_step,
)
from ._deblur import DeblurWidget
from ._diagnose import DiagnoseWidget
from ._learn_family import LearnFamilyWidget
from ._learn_operator import LearnOperatorWidget
from ._pick_beads import PickBeadsWidget
from ._review_patches import ReviewPatchesWidget
from ._view import SideBySide
from ._volume import Volume3DWidget

if TYPE_CHECKING:
    import napari

#: (tab title, widget class, what the step needs, in words for its page).
STEPS = (
    ("Beads", PickBeadsWidget, "an image layer: open a bead image (File > Open, or drag "
                               "it onto the canvas)"),
    ("Review", ReviewPatchesWidget, "a beads layer: detect beads in the Beads step first"),
    ("Model", LearnOperatorWidget, "an image layer: open a bead image"),
    ("Diagnose", DiagnoseWidget, "an image layer: open a bead image"),
    ("Family", LearnFamilyWidget, "several images: a z-stack, or two or more 2-D images"),
    ("Deblur", DeblurWidget, "a learnt model or family: run the Model or Family step, or "
                             "open a model file"),
    ("3D", Volume3DWidget, "a z-stack image layer (Z, Y, X)"),
)
#: Widest the dock asks for (px): the canvas keeps the rest of a 1280 px screen.
PANEL_WIDTH = 380
#: Tabs shown only when their step can run (the others say why in their page).
HIDDEN_UNLESS_READY = ("Family",)
#: Padding of a tab's label (px, left and right): seven whole labels in the dock's width.
TAB_PADDING = 5


def _has(viewer, test) -> bool:
    return any(test(layer) for layer in viewer.layers)


def _is_image(layer) -> bool:
    return is_input_image(layer)


def _is_stack(layer) -> bool:
    return is_input_image(layer, 3)


def _is_beads(layer) -> bool:
    return isinstance(layer, Points) and (layer.name == BEADS or "status" in layer.features)


def _is_model(layer) -> bool:
    meta = layer.metadata or {}
    return OPERATOR_KEY in meta or SUBSPACE_KEY in meta


def _several_images(viewer) -> bool:
    """A stack of two planes or more, or two 2-D images or more of one shape: a family's
    input (results, such as a bead gallery or a map, are not images to learn from)."""
    if any(layer.data.shape[0] >= 2 for layer in input_images(viewer, 3)):
        return True
    shapes = [tuple(layer.data.shape) for layer in input_images(viewer, 2)]
    return any(shapes.count(shape) >= 2 for shape in set(shapes))


#: What lets each step run (a test on the viewer).
NEEDS = {
    "Beads": lambda viewer: _has(viewer, _is_image),
    "Review": lambda viewer: _has(viewer, _is_beads),
    "Model": lambda viewer: _has(viewer, _is_image),
    "Diagnose": lambda viewer: _has(viewer, _is_image),
    "Family": _several_images,
    "Deblur": lambda viewer: _has(viewer, _is_model),
    "3D": lambda viewer: _has(viewer, _is_stack),
}


#: Characters a choice box shows before it elides: a long layer name ("sp8_series045_
#: beads_zyx_uint8") widens neither the box nor the dock; the list shows it whole.
CHOICE_CHARACTERS = 14


def narrow(step) -> None:
    """Keep a step's page within the dock: its choice boxes sized to
    :data:`CHOICE_CHARACTERS`, not to their longest item, and its lines of text (magicgui
    ``Label`` widgets) wrapped."""
    from magicgui.widgets import Container, Label

    for box in step.native.findChildren(QComboBox):
        box.setSizeAdjustPolicy(
            QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        box.setMinimumContentsLength(CHOICE_CHARACTERS)
    for widget in step:
        if isinstance(widget, Label) and widget.name != "hint":
            widget.native.setWordWrap(True)
        elif isinstance(widget, Container):
            narrow(widget)


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
        self.needs: dict = {}  # the line in each page that says what the step needs
        self.pages: dict = {}
        self.view = SideBySide(viewer)
        self.side_by_side = QCheckBox("side by side")
        self.side_by_side.setChecked(self.view.on)
        self.side_by_side.setToolTip(
            "Show a step's result maps beside its input, each in a cell of napari's grid "
            "with its name, colour bar and the scale bar. Unticked (or on Beads and "
            "Review), your own grid setting and layers are as you left them.")
        self.side_by_side.toggled.connect(self.view.set_on)
        for title, cls, need in STEPS:
            widget = cls(viewer)
            widget.side_view = self.view  # each step shows its results through it
            self.steps[title] = widget
            narrow(widget)
            note = QLabel(f"{title} needs {need}.")
            note.setWordWrap(True)
            note.setStyleSheet("QLabel { padding: 6px; color: #ffcc66; }")
            self.needs[title] = note
            scroll = QScrollArea()
            scroll.setWidgetResizable(True)
            scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
            scroll.setWidget(widget.native)
            page = QWidget()
            box = QVBoxLayout(page)
            box.setContentsMargins(0, 0, 0, 0)
            box.addWidget(note)
            box.addWidget(scroll)
            clear = QPushButton(f"Remove the {title} step's layers")
            clear.setToolTip("Remove every layer this step made; the data and the other "
                             "steps' layers stay.")
            clear.clicked.connect(lambda _=False, t=title: self.clear_step(t))
            box.addWidget(clear)
            self.clear_buttons[title] = clear
            self.tabs.addTab(page, title)
            self.pages[title] = page
        self.tabs.tabBar().setStyleSheet(
            f"QTabBar::tab {{ padding-left: {TAB_PADDING}px; padding-right: {TAB_PADDING}px; "
            f"min-width: 0px; }}")
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.side_by_side)
        layout.addWidget(self.tabs)
        self.setMaximumWidth(PANEL_WIDTH + 80)
        self._fit_width()
        self.setMinimumHeight(0)
        self._refit = QTimer(self)  # the panel's own: gone with it, never fired after
        self._refit.setSingleShot(True)
        self._refit.setInterval(0)
        self._refit.timeout.connect(self._fit_width)
        # one radius for every step: the one set in Beads
        self.steps["Beads"].radius.value_edit.changed.connect(self._share_radius)
        viewer.layers.events.inserted.connect(self.update_steps)
        viewer.layers.events.removed.connect(self.update_steps)
        viewer.layers.events.changed.connect(self.update_steps)
        self.update_steps()
        self.tabs.setCurrentIndex(0)  # the method's first step
        self.tabs.currentChanged.connect(self._fit_width)
        self.tabs.currentChanged.connect(self._on_tab)

    def sizeHint(self):  # noqa: N802 (Qt's name)
        hint = super().sizeHint()
        hint.setWidth(min(hint.width(), PANEL_WIDTH))
        hint.setHeight(min(hint.height(), 400))
        return hint

    def minimumSizeHint(self):  # noqa: N802 (Qt's name)
        hint = super().minimumSizeHint()
        hint.setHeight(min(hint.height(), 200))
        return hint

    def _fit_width(self, *_) -> None:
        """Never narrower than the widest step's content (its choices change it: a long
        layer name): dragging the dock narrower would cut its controls, the scroll
        areas scroll vertically only."""
        bar = self.style().pixelMetric(QStyle.PixelMetric.PM_ScrollBarExtent)
        need = max(w.native.minimumSizeHint().width() for w in self.steps.values())
        self.setMinimumWidth(min(need + bar + 8, PANEL_WIDTH + 80))

    def _share_radius(self, *_) -> None:
        source = self.steps["Beads"].radius
        for title in ("Review", "Model", "Diagnose", "Family", "3D"):
            edit = getattr(self.steps[title], "radius", None)
            if edit is not None and edit is not source:
                edit.set_calibration(edit.pixel_size, source.pixels)

    def hideEvent(self, event):  # noqa: N802 (Qt's name)
        """The panel closed (or its dock hidden): the user's own view back, the grid and
        the layers as they were; shown again, the step's view again."""
        self._resume = self.view.active
        self.view.leave()
        super().hideEvent(event)

    def showEvent(self, event):  # noqa: N802 (Qt's name)
        super().showEvent(event)
        if getattr(self, "_resume", False):
            self._resume = False
            self.view.show_tab(self.tabs.tabText(self.tabs.currentIndex()))

    def _on_tab(self, index: int) -> None:
        """The view follows the page: the step's results side by side, or the user's
        own view back."""
        self.view.show_tab(self.tabs.tabText(index))

    def clear_step(self, title: str) -> int:
        """Remove the layers the step ``title`` made (one group); how many went. The
        view then shows what is left (the user's own view, once no map is)."""
        gone = remove_step(self._viewer, title)
        self.view.show_tab(self.tabs.tabText(self.tabs.currentIndex()))
        return gone

    def ready_steps(self) -> list[str]:
        """The titles of the steps that can run now."""
        return [title for title, _, _ in STEPS if NEEDS[title](self._viewer)]

    def offered_steps(self) -> list[str]:
        """The titles of the tabs shown now."""
        return [self.tabs.tabText(i) for i in range(self.tabs.count())
                if self.tabs.isTabVisible(i)]

    def update_steps(self, *_) -> None:
        """Each step runs once its input exists; until then its page says what it needs
        and its controls are greyed. Family is shown only with several images."""
        for i, (title, _, need) in enumerate(STEPS):
            ok = NEEDS[title](self._viewer)
            self.needs[title].setVisible(not ok)
            self.steps[title].native.setEnabled(ok)
            self.tabs.setTabToolTip(i, "" if ok else f"{title} needs {need}.")
            if title in HIDDEN_UNLESS_READY:
                self.tabs.setTabVisible(i, ok)
            self.clear_buttons[title].setEnabled(bool(group_layers(self._viewer, title)))
        self._fit_width()
        # again once the steps' own handlers of the same event have changed their texts
        self._refit.start()
        if not self.tabs.isTabVisible(self.tabs.currentIndex()):
            self.tabs.setCurrentIndex(0)


__all__ = ["STEPS", "PsfSpacePanel"]
