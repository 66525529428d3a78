"""Run a core generator off the GUI thread with a progress bar, a Cancel button and
notifications.

The core's long computations are generators that yield
:class:`~napari_psfspace.core.common.progress.Progress` records and return their result. A
:class:`CoreTask` runs one with :func:`napari.qt.threading.thread_worker`:

* ``yielded`` moves the progress bar and the status line;
* the generator is driven by :func:`~napari_psfspace.core.common.progress.responsive`,
  which repeats its latest record every fraction of a second while it works, so that
* Cancel calls ``worker.quit()`` and is honoured at once, in every phase: the job
  stops, the generator is closed after the step it is in, and the result handler is
  never called (so nothing is added or saved);
* a ``ValueError`` from the core (bad parameter, no beads, ...) is caught *in the
  worker* and shown with :func:`napari.utils.notifications.show_error` as its message,
  which says what to change, never as a traceback;
* the result handler runs in the GUI thread (``returned``): only it touches the viewer.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any

from magicgui.widgets import ComboBox, Container, Label, ProgressBar, PushButton
from napari.qt.threading import GeneratorWorker, thread_worker
from napari.utils.notifications import show_error

from .._layers import input_images
from ..core.common.device import DEVICES, gpu_status
from ..core.common.progress import responsive


@dataclass(frozen=True)
class Failure:
    """A core error caught in the worker: its message is for the user."""

    message: str


def _guarded(gen: Generator) -> Generator[Any, None, Any]:
    try:
        return (yield from gen)
    except ValueError as exc:  # the core's input errors (incl. NoBeadsError)
        return Failure(str(exc))


def _drive(job: Generator) -> Generator[Any, None, Any]:
    return (yield from job)


class CoreTask(Container):
    """A progress bar, a status line and a Cancel button that run one job at a time.

    Parameters
    ----------
    start_button : PushButton
        The button that starts the job; disabled while it runs.
    """

    def __init__(self, start_button: PushButton) -> None:
        self._start_button = start_button
        self.progress = ProgressBar(value=0, min=0, max=100, label="progress", visible=False)
        self.cancel = PushButton(text="Cancel", visible=False)
        self.status = Label(value="")
        self.status.native.setWordWrap(True)
        # the whole width of the step (a wrapped label kept its text's natural width,
        # 116 px, and showed half of its second line)
        from qtpy.QtWidgets import QSizePolicy

        self.status.native.setSizePolicy(QSizePolicy.Policy.Expanding,
                                         QSizePolicy.Policy.MinimumExpanding)
        super().__init__(widgets=[self.progress, self.cancel, self.status], labels=False)
        self.cancel.changed.connect(self.request_cancel)
        self.worker: GeneratorWorker | None = None
        self._job: Generator | None = None
        self._cancelled = False

    @property
    def running(self) -> bool:
        """True while a job is under way."""
        return self.worker is not None

    def run(self, gen: Generator, on_result: Callable[[Any], None],
            *, on_cancel: Callable[[], None] | None = None,
            on_progress: Callable[[Any], None] | None = None) -> GeneratorWorker:
        """Run ``gen`` in a worker thread and call ``on_result(value)`` in the GUI thread.

        Parameters
        ----------
        gen : generator
            A core generator (not started) yielding ``Progress`` records.
        on_result : callable
            Receives the generator's return value unless it failed or was cancelled.
        on_cancel : callable, optional
            Called in the GUI thread after a cancellation.
        on_progress : callable, optional
            Called in the GUI thread with each progress record, after the bar moved.

        Returns
        -------
        GeneratorWorker
            Already started.
        """
        if self.worker is not None:
            raise RuntimeError("a job is already running")
        job = _guarded(responsive(gen))
        worker = thread_worker(_drive, start_thread=False)(job)
        self.worker, self._job = worker, job
        self._cancelled = False
        worker.yielded.connect(self._on_progress)
        if on_progress is not None:
            worker.yielded.connect(on_progress)
        worker.returned.connect(lambda value: self._on_returned(value, on_result, on_cancel))
        worker.finished.connect(lambda: self._on_cancel_unanswered(on_cancel))
        worker.aborted.connect(lambda: self._on_aborted(on_cancel))
        worker.finished.connect(self._on_finished)
        self.progress.value = 0
        self.progress.visible = self.cancel.visible = True
        self.cancel.enabled = True
        self._start_button.enabled = False
        self.status.value = "starting..."
        worker.start()
        return worker

    def request_cancel(self) -> None:
        """Ask the running job to stop at its next step."""
        if self.worker is not None:
            self.status.value = "cancelling..."
            self._cancelled = True
            self.cancel.enabled = False
            self.worker.quit()

    def _on_progress(self, rec) -> None:
        fraction = getattr(rec, "fraction", None)
        if fraction is not None:
            self.progress.value = int(round(100 * float(fraction)))
        self.status.value = str(getattr(rec, "message", rec))

    def _on_returned(self, value, on_result, on_cancel=None) -> None:
        if self._cancelled:  # Cancel came after the job's last step: its result is dropped
            self._on_aborted(on_cancel)
            return
        if isinstance(value, Failure):
            self.status.value = "failed: see the notification"
            show_error(value.message)
            return
        try:
            on_result(value)
        except ValueError as exc:  # e.g. saving to a bad path
            self.status.value = "failed: see the notification"
            show_error(str(exc))
        except OSError as exc:
            self.status.value = "failed: see the notification"
            show_error(f"Could not save: {exc}")

    def _on_aborted(self, on_cancel) -> None:
        job, self._job = self._job, None
        if job is not None:  # the core generator's clean-up runs after its step
            job.close()
        self.status.value = "cancelled: nothing was changed"
        if on_cancel is not None:
            on_cancel()

    def _on_cancel_unanswered(self, on_cancel) -> None:
        # a Cancel after the job's last step: napari's worker then emits neither returned
        # nor aborted, only finished (the result is dropped, as for any other Cancel)
        if self._cancelled and self._job is not None:
            self._on_aborted(on_cancel)

    def _on_finished(self) -> None:
        self.worker, self._job = None, None
        self.progress.visible = self.cancel.visible = False
        self._start_button.enabled = True


# ------------------------------------------------------------------ shared widget parts
def image_choices(viewer, ndim: int | None = None) -> Callable[[Any], list]:
    """A ``choices`` callable for a ComboBox listing the viewer's images a step may work
    on (of ``ndim`` dimensions, when given): no result of the plugin's (a gallery, a map,
    a mosaic, a colour bar) is offered as an input."""

    def choices(_widget=None) -> list:
        return [(layer.name, layer) for layer in input_images(viewer, ndim)]

    return choices


def bead_layer_choices(viewer, *, allow_none: bool = False) -> Callable[[Any], list]:
    """Choices for a Points ComboBox: layers with a bead ``status`` first (the default)."""
    from napari.layers import Points

    def choices(_widget=None) -> list:
        pts = [layer for layer in viewer.layers if isinstance(layer, Points)]
        beads = [(p.name, p) for p in pts if "status" in p.features]
        others = [(p.name, p) for p in pts if "status" not in p.features]
        auto = [("(detect automatically)", None)] if allow_none else []
        return beads + auto + others

    return choices


def prefer_beads(combo) -> None:
    """After the layers changed, select the newest bead layer unless one is chosen."""
    value = combo.value
    if value is not None and "status" in value.features:
        return
    options = [v for v in combo.choices if v is not None and "status" in v.features]
    if options:
        combo.value = options[-1]


def device_choice() -> ComboBox:
    """The device a step runs on (auto, cpu, gpu); its tooltip says whether this machine
    has a GPU the package can use, and what installs it where not."""
    combo = ComboBox(label="device", choices=list(DEVICES), value="auto")
    ok, why = gpu_status()
    combo.tooltip = ("auto: the GPU when CuPy sees one, else the CPU. Here: "
                     + ("a GPU." if ok else f"no GPU ({why}); pip install "
                        "'napari-psfspace[gpu]' on a machine with one."))
    return combo


def result_text(lines: int = 8):
    """A read-only text box for a step's result: wraps, scrolls past ``lines`` lines,
    and can be selected and copied. A wrapped ``Label`` in a form layout was clipped to
    half a line (and wider than the dock) once the text grew."""
    from magicgui.widgets import TextEdit

    box = TextEdit(value="")
    box.native.setReadOnly(True)
    height = box.native.fontMetrics().lineSpacing() * lines + 12
    box.native.setMaximumHeight(height)
    box.native.setMinimumHeight(min(height, 4 * box.native.fontMetrics().lineSpacing() + 12))
    return box


class RadiusEdit(Container):
    """The PSF radius, in micrometres when the image is calibrated, else in pixels.

    ``pixels`` gives the value in pixels whatever the display unit.
    """

    def __init__(self, label: str = "PSF radius") -> None:
        from magicgui.widgets import FloatSpinBox

        self._pixel_size: float | None = None
        self._base_label = label
        self.value_edit = FloatSpinBox(value=10.0, min=0.01, max=10000.0, step=0.5,
                                       label=f"{label} (px)")
        self.value_edit.tooltip = (
            "Upper bound of the PSF radius: beyond it the PSF is lost in the noise "
            "(about 3x the FWHM). Beads closer than twice this to each other are not used.")
        # micrometres to 4 decimals (0.1 nm): with Qt's default 2, 14 px of 65 nm showed
        # as 0.91 um and came back as 14.0 px only by luck, 11 px as 10.92
        self.value_edit.native.setDecimals(4)
        self.hint = Label(value="", name="hint")
        # the label sits in the step's own label column: one column for the whole page,
        # not a second one inside this row, which would widen the page past the dock
        super().__init__(widgets=[self.value_edit, self.hint], labels=False,
                         label=f"{label} (px)")
        self.value_edit.changed.connect(self._update_hint)

    @property
    def pixels(self) -> float:
        """The radius in pixels (to 1e-6 px: 0.91 um / 0.065 um is 14.000000000000002,
        whose ceiling, a patch's half-width, would be 15)."""
        v = float(self.value_edit.value)
        return round(v / self._pixel_size, 6) if self._pixel_size else v

    @property
    def pixel_size(self) -> float | None:
        """Pixel size (µm) of the image, or None when it has none."""
        return self._pixel_size

    def set_calibration(self, pixel_size: float | None, radius_px: float | None = None) -> None:
        """Switch units for an image with this pixel size (µm) and show ``radius_px``."""
        r = self.pixels if radius_px is None else float(radius_px)
        self._pixel_size = pixel_size
        if pixel_size:
            self.value_edit.label = self.label = f"{self._base_label} (µm)"
            self.value_edit.step = round(float(pixel_size), 4)
            self.value_edit.value = round(r * pixel_size, 4)
        else:
            self.value_edit.label = self.label = f"{self._base_label} (px)"
            self.value_edit.step = 0.5
            self.value_edit.value = round(r, 2)
        self._update_hint()

    def _update_hint(self, *_: Any) -> None:
        # short, so that the page stays within the dock; the pixel size in the tooltip
        self.hint.value = f"= {self.pixels:.1f} px" if self._pixel_size else ""
        self.hint.tooltip = (f"{self._pixel_size:g} µm a pixel (the image's pixel size)"
                             if self._pixel_size else "")


def pixel_size_of(layer) -> float | None:
    """Pixel size (µm) of an image layer: its metadata, else a non-unit scale, else None."""
    meta = layer.metadata or {}
    scale = float(layer.scale[-1])
    return meta.get("pixel_size_um") or (scale if scale != 1.0 else None)


class FollowsBeads:
    """Mixin for widgets with a ``points`` (beads layer) chooser and a ``radius`` edit.

    The beads layer is the truth downstream of *Pick beads*: the widget prefers it in
    the chooser, and takes its radius whenever the layer changes (a new detection).
    """

    def _on_layers(self, *_) -> None:
        self.reset_choices()
        prefer_beads(self.points)

    def _connect_inputs(self, viewer, on_inputs) -> None:
        """Refresh on a new image or beads choice and when layers come and go."""
        self.points.changed.connect(on_inputs)
        self.image.changed.connect(on_inputs)
        viewer.layers.events.inserted.connect(self._on_layers)
        viewer.layers.events.removed.connect(self._on_layers)
        self._on_layers()
        on_inputs()

    def _follow(self, pts) -> None:
        """Listen to the chosen beads layer (and stop listening to the previous one)."""
        old = getattr(self, "_followed", None)
        if old is pts:
            return
        if old is not None:
            old.events.data.disconnect(self._refresh_radius)
        if pts is not None:
            pts.events.data.connect(self._refresh_radius)
        self._followed = pts

    def _calibrate(self, img, pts) -> None:
        """Pixel size from the image, radius from the beads layer (else the image)."""
        meta = img.metadata or {}
        r = (pts.metadata or {}).get("psf_radius_px") if pts is not None else None
        self.radius.set_calibration(pixel_size_of(img),
                                    r if r is not None else meta.get("psf_radius"))

    def _bead_plane(self, img, pts):
        """The plane the beads were detected on, or None (the user is told why)."""
        from napari.utils.notifications import show_error

        from .._layers import bead_plane

        if img is None:
            self.task.status.value = "Open a bead image first (or File > Open Sample)."
            return None
        try:
            return bead_plane(img, pts, self._viewer.dims.point)
        except ValueError as exc:
            show_error(str(exc))
            return None

    def _bead_diameter_px(self) -> float:
        """The beads' diameter (pixels) given in *Pick beads*, 0 when none."""
        pts = self.points.value
        return float((pts.metadata or {}).get("bead_diameter_px", 0.0)) if pts is not None \
            else 0.0

    def _refresh_radius(self, *_) -> None:
        """Take the radius the beads were detected with."""
        pts = self.points.value
        r = None if pts is None else (pts.metadata or {}).get("psf_radius_px")
        if r is not None and abs(self.radius.pixels - float(r)) > 1e-9:
            self.radius.set_calibration(self.radius.pixel_size, float(r))


def fit_to_width(table) -> None:
    """Set ``table`` (a magicgui Table) to share the dock's width between its columns and
    wrap their texts, its rows as tall as their text: no sideways scroll."""
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QHeaderView, QStyledItemDelegate

    native = table.native
    # Qt's own delegate: each cell's text as written (magicgui's delegate shows a cell
    # that reads as a number in its own float format, e-notation for small errors)
    native.setItemDelegate(QStyledItemDelegate(native))
    native.setWordWrap(True)
    native.setTextElideMode(Qt.TextElideMode.ElideNone)
    native.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
    native.verticalHeader().setVisible(False)
    header = native.horizontalHeader()
    header.setSectionResizeMode(QHeaderView.ResizeMode.Stretch)
    header.sectionResized.connect(lambda *_: native.resizeRowsToContents())


def table_widget(columns: list[str], label: str, tooltip: str):
    """A read-only magicgui Table for the dock, hidden until it has rows: its columns
    share the dock's width and wrap (:func:`fit_to_width`). Show rows with
    :func:`show_rows`."""
    from magicgui.widgets import Table

    table = Table(value={"data": [], "columns": list(columns)}, label=label)
    table.read_only = True
    fit_to_width(table)
    table.tooltip = tooltip
    table.visible = False
    return table


def show_rows(table, value: dict) -> None:
    """Put a Table's value (``data``, ``index``, ``columns``), its rows as tall as their
    text; shown when it has rows."""
    table.value = value
    table.native.resizeRowsToContents()
    table.visible = bool(value["data"])
