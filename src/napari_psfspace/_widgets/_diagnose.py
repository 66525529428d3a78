"""Dock widget 4: diagnose the model on the beads, show what it lacked, write a report."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    FloatSpinBox,
    PushButton,
)
from napari.utils.notifications import show_info

from .._layers import (
    OPERATOR_KEY,
    Frame,
    LayerTuple,
    map_tuple,
    on_field,
    show_layers,
    user_beads,
)
from ..core.diagnosis.loop import iter_diagnose
from ..report import (
    STEP_COLUMNS,
    figure_arrays,
    model_lines,
    steps_table,
    summary_text,
    write_report,
)
from ._view import show_step
from ._worker import (
    CoreTask,
    FollowsBeads,
    RadiusEdit,
    bead_layer_choices,
    image_choices,
    result_text,
    show_rows,
    table_widget,
)

if TYPE_CHECKING:
    import napari

#: Names of the layers this widget creates.
MAP_BEFORE = "excess error, plain model (%)"
MAP_AFTER = "excess error, final model (%)"
MEAN_BEFORE = "mean residual, plain (noise sd)"
MEAN_AFTER = "mean residual, final (noise sd)"
#: The steps table's columns in the dock, each the report's column it shows and its
#: header here: the report (``write report to``) holds every column.
DOCK_COLUMNS = {"effect": "effect", "held-out error": "held-out\nerror",
                "chi2/dof": "misfit /\nnoise", "decision": "decision"}


def dock_cell(text: str) -> str:
    """A report cell as the dock's narrow columns show it: its numbers to three
    significant digits, "a -> b" on two lines, the effects in words ("hot pixels"): a
    cell wraps at spaces only, and a long number would be cut."""
    text = re.sub(r"-?\d+\.\d+(?:e[-+]?\d+)?",
                  lambda m: f"{float(m.group()):.3g}", text)
    return text.replace(" -> ", "\n-> ").replace("_", " ")


def dock_table(rows: list[list[str]]) -> dict:
    """A magicgui Table's value: the steps' rows (:func:`steps_table`, in the order of
    ``STEP_COLUMNS``) cut to :data:`DOCK_COLUMNS`, each cell :func:`dock_cell`."""
    at = [STEP_COLUMNS.index(c) for c in DOCK_COLUMNS]
    data = [[dock_cell(row[i]) for i in at] for row in rows]
    return {"data": data, "index": list(range(len(rows))),
            "columns": list(DOCK_COLUMNS.values())}


#: The residual tests table's columns.
TEST_COLUMNS = ("residual test", "plain\nmodel", "final\nmodel")


def tests_table(diagnosis) -> dict:
    """A magicgui Table's value: each residual test significant on the plain or the
    final model, its strength over its threshold on each (above 1: significant), the
    strongest on the plain model first."""
    before, after = diagnosis.analysis_before, diagnosis.analysis_after
    names = [t.name for t in before.significant()]
    names += [t.name for t in after.significant() if t.name not in names]
    rows = []
    for name in names:
        cells = []
        for analysis in (before, after):
            test = analysis.tests.get(name)
            cells.append("-" if test is None else f"{test.evidence:.2f}")
        rows.append([name.replace("_", " "), *cells])
    return {"data": rows, "index": list(range(len(rows))),
            "columns": list(TEST_COLUMNS)}


def diagnosis_layers(diagnosis, frame: Frame) -> list[LayerTuple]:
    """Layer-data tuples of the residual maps and the mean residual patches, before and
    after, each on the image's field: the two maps on one colour scale, the two patches
    (magnified) on one grey scale.

    Parameters
    ----------
    diagnosis : Diagnosis
    frame : Frame
        The image's frame.

    Returns
    -------
    list of (data, kwargs, layer_type)
    """
    fig = figure_arrays(diagnosis)
    cell = fig["cell_size"]
    about_map = ("held-out excess error of each bead, in % of its energy (its relative "
                 "residual energy minus its noise floor), painted as a disk at its place; "
                 "NaN: no bead")
    out: list[LayerTuple] = []
    for name, key in ((MAP_BEFORE, "map_before"), (MAP_AFTER, "map_after")):
        meta = {"about": about_map, "cell_size_px": cell}
        if key == "map_after":  # the model the diagnosis refined: Deblur offers it
            meta[OPERATOR_KEY] = diagnosis.operator
            meta["model_label"] = "Diagnose's final model"
        m = (100.0 * fig[key]).astype("float32")  # in % of each bead's energy
        out.append(map_tuple(m, {"name": name, **on_field(frame, m.shape, fill=1.0),
                                 "colormap": "viridis",
                                 "contrast_limits": (0.0, 100.0 * fig["map_limit"]),
                                 "metadata": meta}, "%", frame))
    lim = fig["mean_limit"]
    for name, key in ((MEAN_BEFORE, "mean_before"), (MEAN_AFTER, "mean_after")):
        patch = fig[key].astype("float32")
        out.append(map_tuple(patch, {
            "name": name, **on_field(frame, patch.shape, fill=1.0), "colormap": "gray",
            "contrast_limits": (-lim, lim),
            "metadata": {"about": "mean normalised residual patch over the beads (noise "
                                  "sd), magnified"}}, "sd", frame))
    return out


class DiagnoseWidget(FollowsBeads, Container):
    """Trace the held-out residual of the model to what it lacks, add it, report.

    Runs :func:`~napari_psfspace.core.diagnosis.loop.iter_diagnose` on the image (the slice and
    radius of the chosen beads layer; the beads are detected and centred again), then
    shows the table of steps, the residual maps and the mean residual patches before and
    after, and writes the report (report.md, report.json, figures) when a folder is given.
    """

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self._viewer = viewer
        self.image = ComboBox(label="image", choices=image_choices(viewer))
        self.points = ComboBox(label="beads", choices=bead_layer_choices(viewer, allow_none=True))
        self.points.tooltip = ("Its slice and PSF radius are used. Diagnose detects and "
                               "centres the beads itself.")
        self.radius = RadiusEdit()
        self.threshold = FloatSpinBox(value=8.0, min=0.5, max=1000.0, step=0.5,
                                      label="threshold")
        self.threshold.tooltip = "Detection threshold (noise sd of the filtered image)."
        self.camera = CheckBox(value=False, text="camera values known")
        self.camera.tooltip = ("Off: the noise model is measured on the image (photon "
                               "transfer).")
        self.gain = FloatSpinBox(value=2.0, min=1e-4, max=1e4, step=0.1,
                                 label="gain (ADU/e-)", visible=False)
        self.offset = FloatSpinBox(value=100.0, min=-1e6, max=1e6, step=1.0,
                                   label="offset (ADU)", visible=False)
        self.read_noise = FloatSpinBox(value=1.5, min=0.0, max=1e4, step=0.1,
                                       label="read noise (e-)", visible=False)
        self.report_dir = FileEdit(mode="d", label="write report to")
        self.report_dir.tooltip = "Folder for report.md, report.json and figures (optional)."
        self.diagnose = PushButton(text="Diagnose")
        self.task = CoreTask(self.diagnose)
        self.result = result_text()
        self.table = table_widget(
            list(DOCK_COLUMNS.values()), "steps",
            "Each effect tried, the held-out error and the misfit over the noise before "
            "-> after it; the report holds the tests and their p-values.")
        self.tests = table_widget(
            list(TEST_COLUMNS), "tests",
            "The residual tests that find structure beyond the noise, each as its "
            "strength over its threshold (above 1: significant) on the plain and the "
            "final model.")
        self.remove_motion = CheckBox(value=False, text="remove motion blur")
        self.remove_motion.tooltip = (
            "Motion blur (a smear common to all beads) is always looked for and reported; "
            "tick to divide it out of the refined model (the sample was still).")
        super().__init__(widgets=[
            self.image, self.points, self.radius, self.threshold, self.camera, self.gain,
            self.offset, self.read_noise, self.remove_motion, self.report_dir,
            self.diagnose, self.task,
            self.result, self.table, self.tests])
        self.diagnosis = None
        self.camera.changed.connect(self._on_camera)
        self.diagnose.changed.connect(self.run)
        self._connect_inputs(viewer, self._on_inputs)

    def _on_camera(self, on: bool) -> None:
        for w in (self.gain, self.offset, self.read_noise):
            w.visible = bool(on)

    def _on_inputs(self, *_) -> None:
        img, pts = self.image.value, self.points.value
        self._follow(pts)
        if img is None:
            return
        self._calibrate(img, pts)

    def run(self, *_) -> None:
        """Diagnose in a worker thread; show the steps and maps, write the report."""
        img, pts = self.image.value, self.points.value
        got = self._bead_plane(img, pts)
        if got is None:
            return
        plane, frame = got
        camera = {}
        if self.camera.value:
            camera = {"gain": float(self.gain.value), "offset": float(self.offset.value),
                      "read_noise": float(self.read_noise.value)}
        folder = (Path(self.report_dir.value)
                  if str(self.report_dir.value) not in ("", ".") else None)
        name = img.name
        beads = None
        if pts is not None:  # the user's beads (rejections by hand, masked pixels)
            beads = user_beads(self._viewer, pts, frame)[0]
        gen = iter_diagnose(plane, psf_radius=self.radius.pixels,
                            threshold=float(self.threshold.value),
                            bead_diameter=self._bead_diameter_px(),
                            remove_motion=bool(self.remove_motion.value), beads=beads,
                            **camera)

        def on_result(diag) -> None:
            self.diagnosis = diag
            rows = steps_table(diag)
            show_rows(self.table, dock_table(rows))
            show_rows(self.tests, tests_table(diag))
            self.result.value = "\n".join([summary_text(diag),
                                           *model_lines(diag.operator.metadata,
                                                        markdown=False)])
            show_layers(self._viewer, diagnosis_layers(diag, frame), step="Diagnose",
                        replace=True)
            show_step(self, "Diagnose", img)
            if folder is not None:
                path = write_report(diag, folder, image_name=name,
                                    pixel_size=frame.pixel_size,
                                    extra={"slice": frame.index})
                show_info(f"Report written to {path}")
                self.result.value += f"\nreport: {path}"

        self.task.run(gen, on_result)
