"""Dock widget 7: space-varying 3D PSFs from a bead z-stack, and 3D deblurring.

*Learn 3D PSF* runs :func:`~napari_psfspace.core.volume.estimate3d.iter_estimate_operator_3d`
on a z-stack layer (the voxel size from the layer's scale) and shows:

- the 3D PSF grid (the PSF at 5 x 5 field positions, tiled) as a volume on the stack's
  own z axis, its bead plane on the stack's bead plane: scrolling through z, or the 3D
  view, shows how focus and shape change over the field;
- its sections through focus (z down, x across; z down, y across): the orthogonal views
  of each PSF;
- the maps over the field of the focal shift, the lateral and axial FWHM and the
  astigmatic split, each with a colour bar, beside the stack.

*Deblur 3D* runs :func:`~napari_psfspace.core.volume.deconvolve3d.iter_richardson_lucy_3d`
(float32, on blocks) with the learnt model or a model file, on any z-stack layer of the
model's lateral size. Both run in a worker with progress and Cancel; only the result
handlers touch the viewer.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    FloatSpinBox,
    Label,
    PushButton,
    SpinBox,
)
from napari.layers import Image
from napari.utils.notifications import show_error

from .._layers import Frame, axis_unit, map_tuple, on_field, show_layers
from ..core.common.measures import in_units, psf_measures
from ..core.common.progress import Progress
from ..core.volume import iter_estimate_operator_3d, load_operator_3d
from ..core.volume.deconvolve3d import (
    MIN_ITERATIONS,
    STOP_FIT,
    iter_richardson_lucy_3d,
)
from ..core.volume.measures import measure_maps
from ..core.volume.views import psf_grid_3d
from ._view import show_step
from ._worker import CoreTask, RadiusEdit, device_choice, result_text

if TYPE_CHECKING:
    import napari

STEP = "3D"
PSF_GRID_3D = "3D PSF grid"
PSF_SECTIONS = "x-z sections"
PSF_SECTIONS_Y = "y-z sections"
DEBLURRED_3D = "deblurred 3D"
#: The panel's cap on Deblur 3D's iterations: with the acceleration, the stopping rule
#: ends before it on the measured stacks, and the time estimate (for the cap) stays near
#: the time taken (bench/bench_deblur3d_panel.py).
PANEL_ITERATIONS = 25
#: The deblurred stack's group: removed with the step's other layers, not replaced by a
#: new Learn.
DEBLUR_STEP = f"{STEP}/deblur"
OPERATOR_3D_KEY = "psfspace_operator_3d"
#: (measure, layer name without its unit, colormap) of the maps shown; the unit (µm where
#: the stack's voxel size is known, else px and planes) is added to the name.
MAPS = (("focal_plane", "focal shift", "coolwarm"),
        ("fwhm_lateral", "lateral FWHM", "viridis"),
        ("fwhm_axial", "axial FWHM", "viridis"),
        ("astigmatic_split", "astigmatic split", "PiYG"))


def map_in_units(key: str, values: np.ndarray, plane: int, voxel) -> tuple[np.ndarray, str]:
    """A measure map as shown: the focal shift from the bead plane; µm where ``voxel``
    ``(dz, dy, dx)`` in µm is known, else px and planes. Returns the map and its unit."""
    m = values.astype(np.float64) - (plane if key == "focal_plane" else 0.0)
    if voxel is None:
        return m.astype(np.float32), "px" if key == "fwhm_lateral" else "planes"
    step = voxel[1] if key == "fwhm_lateral" else voxel[0]
    return (m * step).astype(np.float32), "µm"


def map_limits(key: str, m: np.ndarray) -> tuple[float, float]:
    """Contrast limits of a map: its finite range; a flat map (one PSF for the field) gets
    its value mid-bar; signed measures (focal shift, astigmatic split) a range symmetric
    about 0."""
    finite = m[np.isfinite(m)]
    if not finite.size:
        return 0.0, 1.0
    lo, hi = float(finite.min()), float(finite.max())
    if key in ("focal_plane", "astigmatic_split"):
        top = max(abs(lo), abs(hi))
        return (-top, top) if top > 0 else (-1.0, 1.0)
    if hi - lo < 1e-3 * max(abs(lo), abs(hi), 1e-12):
        pad = 0.05 * max(abs(lo), 1e-12)
        return lo - pad, hi + pad
    return lo, hi


def on_stack_planes(volume: np.ndarray, plane: int, n_planes: int) -> np.ndarray:
    """The 3D PSF grid (K planes, its bead plane at K // 2) on the stack's own planes:
    plane ``j`` of the result is the grid's plane ``K // 2 + j - plane``, zero where
    the grid has none."""
    k = volume.shape[0]
    out = np.zeros((n_planes, *volume.shape[1:]), np.float32)
    j = np.arange(n_planes)
    src = k // 2 + j - int(plane)
    ok = (src >= 0) & (src < k)
    out[j[ok]] = volume[src[ok]]
    return out


def stack_of(layer) -> tuple[np.ndarray, tuple, tuple]:
    """A z-stack layer's data, scale and translate (z, y, x); ValueError naming the layer
    unless it is one. An array in memory is copied for the worker; a lazy one (dask, a
    Zarr store; the full resolution of a multiscale layer) is passed as it is, read by
    the worker, not by the viewer's thread."""
    if layer is None:
        raise ValueError("image: open a z-stack (Z, Y, X) first")
    data = layer.data[0] if getattr(layer, "multiscale", False) else layer.data
    if getattr(layer, "rgb", False) or len(np.shape(data)) != 3:
        raise ValueError(f"image: layer {layer.name!r} has shape {np.shape(data)}; "
                         f"a z-stack (Z, Y, X) is expected")
    if isinstance(data, np.ndarray):
        data = np.array(data, copy=True)
    return (data, tuple(float(s) for s in layer.scale),
            tuple(float(t) for t in layer.translate))


def _in_memory(stack):
    """The stack as an ndarray (a lazy layer's read here, in the worker)."""
    if not isinstance(stack, np.ndarray):
        yield Progress("read", 0.0, "reading the z-stack")
        stack = np.asarray(stack)
    return stack


def _learn(stack, voxel, **kwargs):
    """Estimate, then the views (in the worker)."""
    stack = yield from _in_memory(stack)
    est = yield from iter_estimate_operator_3d(stack, voxel_size=voxel, **kwargs)
    yield Progress("views", 1.0, "PSF grid and maps")
    grid = psf_grid_3d(est.operator, 5)
    maps = measure_maps(est.operator, 8, 8)
    _, h, w = est.operator.image_shape
    centre = psf_measures(est.operator.psf_at((h - 1) / 2, (w - 1) / 2))
    values, units = in_units(centre, voxel)
    for name, unit in units.items():  # the panel's unit: µm
        if unit == "nm":
            values[name], units[name] = values[name] / 1000.0, "µm"
    return est, grid, maps, (values, units), stack  # the stack read, for the report


def _report(est, stack, voxel, folder, na, wavelength_nm, name):
    """The QC record and its files (in the worker)."""
    from ..report.qc import qc_record
    from ..report.qc_page import write_qc_report

    yield Progress("report", 0.0, "measuring the field, the beads and the theory")
    rec = qc_record(est, stack, voxel_size=voxel,
                    sampling_from="the layer's scale" if voxel else "unknown", na=na,
                    wavelength_nm=wavelength_nm, source=name)
    yield Progress("report", 0.8, "writing the page")
    return rec, write_qc_report(rec, est, folder, voxel)


def deblurred_layers(res, layer, scale, translate) -> list:
    """The deblurred stack where the input lies (the same planes and field: side by
    side, the z slider and the camera act on both), in the input's colormap."""
    _, h, w = np.shape(res.volume)
    frame = Frame((h, w), tuple(scale[1:]), tuple(translate[1:]), units=axis_unit(layer))
    vol = np.asarray(res.volume, np.float32)
    top = float(np.percentile(vol, 99.99)) if vol.size else 1.0
    cmap = getattr(getattr(layer, "colormap", None), "name", None) or "gray"
    return [map_tuple(vol, {
        "name": f"{DEBLURRED_3D} (image units)", "scale": scale, "translate": translate,
        "colormap": cmap, "contrast_limits": (0.0, max(top, 1e-12)),
        "metadata": {"source": layer.name, "iterations": res.iterations,
                     "background": res.background}}, "", frame)]


def estimate_line(rec) -> str | None:
    """The deblur's line under the 3D page for a progress record: the time estimate made
    before the iterations ("estimate: " and the record's message), cleared once they run
    (the progress line then says how long is left, measured), else None (unchanged): one
    estimate on the page at a time."""
    stage = getattr(rec, "stage", "")
    if stage == "estimate":
        return f"estimate: {rec.message}"
    if stage == "iteration":
        return ""
    return None


class Volume3DWidget(Container):
    """Learn a space-varying 3D PSF from a bead z-stack; deblur a z-stack with it."""

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self._viewer = viewer
        self.image = ComboBox(label="z-stack", choices=self._stacks)
        self.radius = RadiusEdit()
        self.radius.value_edit.tooltip = (
            "Lateral radius of the 3D PSF (the widest plane kept): µm for a calibrated "
            "stack, else px. The panel sets it from the Beads step's radius.")
        self.radius.set_calibration(None, 16.0)
        self.z_radius = FloatSpinBox(label="z radius (planes)", min=0.0, max=1e4, value=0.0)
        self.z_radius.tooltip = ("Depth kept on each side of the bead plane: µm for a "
                                 "calibrated stack, else planes (0: all).")
        self._z_step: float | None = None
        self.n_psf = SpinBox(label="PSF basis size", min=0, max=50, value=0)
        self.n_psf.tooltip = "Number of 3D kernels, I in the paper (0: chosen from the data)."
        self.learn = PushButton(text="Learn 3D PSF")
        self.learn_task = CoreTask(self.learn)
        self.learn_result = result_text(6)
        self.model_file = FileEdit(mode="r", filter="*.npz", label="or model file")
        self.iterations = SpinBox(label="iterations at most", min=1, max=10000,
                                  value=PANEL_ITERATIONS)
        self.accelerate = CheckBox(value=True, text="accelerate")
        self.accelerate.tooltip = ("Each step starts from an extrapolation of the last "
                                   "two (Biggs-Andrews): the same fixed point in fewer "
                                   "iterations.")
        self.stop = CheckBox(value=True, text="stop when the fit stops improving")
        self.stop.tooltip = (f"Ends when an iteration improves the fit to the data "
                             f"(Poisson deviance) by less than {STOP_FIT:g} of itself, "
                             f"after {MIN_ITERATIONS} iterations at least.")
        self.device = device_choice()
        self.deblur = PushButton(text="Deblur 3D")
        self.deblur_task = CoreTask(self.deblur)
        self.deblur_result = Label(value="")
        self.deblur_result.native.setWordWrap(True)
        self.na = FloatSpinBox(label="NA", min=0.0, max=1.7, step=0.01,
                               value=0.0)
        self.wavelength = FloatSpinBox(label="emission (nm)", min=0.0,
                                       max=2000.0, step=1.0, value=0.0)
        for box in (self.na, self.wavelength):
            box.tooltip = ("0: not given. With both, the report sets the widths beside "
                           "theory (Abbe, and an aberration-free pupil PSF) and judges "
                           "them.")
        self.report_dir = FileEdit(mode="d", label="report folder")
        self.report = PushButton(text="Report")
        self.report.tooltip = ("Write qc.html (figures inline), qc_beads.csv and qc.json "
                               "of the learnt 3D PSF into the report folder.")
        self.report_task = CoreTask(self.report)
        self.report_result = Label(value="")
        self.report_result.native.setWordWrap(True)
        super().__init__(widgets=[
            self.image, self.radius, self.z_radius, self.n_psf, self.learn,
            self.learn_task, self.learn_result, self.na, self.wavelength, self.report_dir,
            self.report, self.report_task, self.report_result, self.model_file,
            self.iterations, self.accelerate, self.stop, self.device, self.deblur,
            self.deblur_task, self.deblur_result])
        self.operator = None
        self._learnt = None  # (estimation, stack, voxel size, stack name) of the last Learn
        self.report.changed.connect(self.run_report)
        self.learn.changed.connect(self.run_learn)
        self.image.changed.connect(self._calibrate)
        self._calibrate()
        self.deblur.changed.connect(self.run_deblur)
        viewer.layers.events.inserted.connect(lambda *_: self.reset_choices())
        viewer.layers.events.removed.connect(lambda *_: self.reset_choices())

    def _calibrate(self, *_) -> None:
        """µm for a calibrated stack (its lateral and z steps), else px and planes."""
        layer = self.image.value
        scale = (1.0, 1.0, 1.0) if layer is None else tuple(float(v) for v in layer.scale)
        calibrated = not np.allclose(scale, 1.0)
        self.radius.set_calibration(scale[-1] if calibrated else None)
        planes = self.z_planes()
        self._z_step = scale[0] if calibrated else None
        self.z_radius.label = "z radius (µm)" if calibrated else "z radius (planes)"
        self.z_radius.value = planes * (self._z_step or 1.0)

    def z_planes(self) -> int:
        """The z radius in planes (0: all)."""
        return int(round(float(self.z_radius.value) / (self._z_step or 1.0)))

    def _stacks(self, _widget=None) -> list:
        return [(layer.name, layer) for layer in self._viewer.layers
                if isinstance(layer, Image) and layer.ndim == 3
                and not getattr(layer, "rgb", False)]

    def _fail(self, exc: Exception, task: CoreTask) -> None:
        show_error(str(exc))
        task.status.value = str(exc)

    def run_learn(self, *_) -> None:
        """Learn the 3D model in a worker; show the PSF grid, its sections and maps."""
        try:
            stack, scale, translate = stack_of(self.image.value)
        except ValueError as exc:
            self._fail(exc, self.learn_task)
            return
        voxel = None if np.allclose(scale, 1.0) else scale
        gen = _learn(stack, voxel, psf_radius=float(self.radius.pixels),
                     z_radius=self.z_planes() or None,
                     n_psf=int(self.n_psf.value) or None)

        def on_result(got) -> None:
            est, (_, _, volume, sections, sections_y), (_, _, maps), (c, u), read = got
            self.operator = op = est.operator
            self._learnt = (est, read, voxel, self.image.value.name)
            self._show(op, volume, (sections, sections_y), maps, scale, translate,
                       stack.shape[0])
            meta = op.metadata
            self.learn_result.value = (
                f"{op.n_psf} 3D PSFs in the basis, of {'x'.join(map(str, op.kernel_shape))} "
                f"voxels, from "
                f"{meta.get('n_beads_used', '?')} beads; bead plane {op.plane}\n"
                f"field model: {meta.get('field_model', 'space-varying')}"
                + (f" ({meta['field_model_reason']})" if meta.get("field_model_reason")
                   else "")
                + f"\nat the centre (Gaussian fits): lateral FWHM {c['fwhm_lateral']:.3g} "
                  f"{u['fwhm_lateral']}, axial {c['fwhm_axial']:.3g} {u['fwhm_axial']}, "
                  f"ellipticity {c['ellipticity']:.2f}")
            held = meta.get("heldout") or {}
            if held.get("n_beads"):
                self.learn_result.value += (
                    f"\nheld-out beads ({held['n_beads']}): residual "
                    f"{held['residual_median']:.3f}, {held['over_floor']:.2f}x the noise "
                    f"floor; one 3D PSF {held['single_median']:.3f}")

        self.learn_task.run(gen, on_result)

    def run_report(self, *_) -> None:
        """Write the QC report of the last Learn into the report folder, in a worker."""
        folder = str(self.report_dir.value)
        if self._learnt is None:
            self._fail(ValueError("Report: learn a 3D PSF first"), self.report_task)
            return
        if folder in ("", "."):
            self._fail(ValueError("report folder: choose a folder to write the report in"),
                       self.report_task)
            return
        est, stack, voxel, name = self._learnt
        na = float(self.na.value) or None
        wl = float(self.wavelength.value) or None

        def on_result(got) -> None:
            rec, paths = got
            verdict = {True: "PASS", False: "FAIL", None: "not judged"}[rec["passed"]]
            self.report_result.value = (
                f"wrote {paths['html']} (and qc_beads.csv, qc.json): {verdict}"
                + "".join(f"\nwarning: {w}" for w in rec["warnings"]))

        self.report_task.run(_report(est, stack, voxel, folder, na, wl, name), on_result)

    def _show(self, op, volume, sections, maps, scale, translate, n_planes) -> None:
        dz, dy, dx = scale
        tz, ty, tx = translate
        _, h, w = op.image_shape
        frame = Frame((h, w), (dy, dx), (ty, tx), units=axis_unit(self.image.value))
        voxel = None if np.allclose(scale, 1.0) else scale
        rel = "relative"
        grid = on_field(frame, volume.shape[1:], fill=1.0)
        tuples = [map_tuple(on_stack_planes(volume, op.plane, n_planes), {
            "name": f"{PSF_GRID_3D} ({rel})", "scale": (dz, *grid["scale"]),
            "translate": (tz, *grid["translate"]),
            "colormap": "magma", "contrast_limits": (0.0, 1.0),
            "metadata": {OPERATOR_3D_KEY: op,
                         "about": "3D PSF at 5 x 5 field positions on the stack's planes, "
                                  "each scaled to its maximum, gamma 0.5"}}, "", frame)]
        # the sections in their true aspect (z step over lateral step), magnified
        # together to fill the field
        s = grid["scale"][0]
        for name, sec in ((PSF_SECTIONS, sections[0]), (PSF_SECTIONS_Y, sections[1])):
            aspect = dz / dy
            fit = min(frame.height / (sec.shape[0] * s * aspect),
                      frame.width / (sec.shape[1] * s))
            sy, sx = s * aspect * fit, s * fit
            y0 = ty - dy / 2 + (frame.height - sec.shape[0] * sy) / 2
            x0 = tx - dx / 2 + (frame.width - sec.shape[1] * sx) / 2
            tuples.append(map_tuple(sec, {
                "name": f"{name} ({rel})", "scale": (sy, sx),
                "translate": (y0 + sy / 2, x0 + sx / 2), "colormap": "magma",
                "contrast_limits": (0.0, 1.0),
                "metadata": {"about": f"{name} of the 3D PSF grid (z down), true aspect "
                                      "ratio"}},
                "", frame))
        for key, label, cmap in MAPS:
            m, unit = map_in_units(key, maps[key], op.plane, voxel)
            tuples.append(map_tuple(np.nan_to_num(m, nan=0.0), {
                "name": f"{label} ({unit})", **on_field(frame, m.shape, fill=1.0),
                "colormap": cmap, "contrast_limits": map_limits(key, m)}, unit, frame))
        show_layers(self._viewer, tuples, step=STEP, replace=True)
        show_step(self, STEP, self.image.value)

    def model(self):
        """The model to deblur with: the file when one is chosen, else the learnt one."""
        path = str(self.model_file.value)
        if path not in ("", "."):
            return load_operator_3d(Path(path))
        if self.operator is None:
            raise ValueError("model: learn a 3D PSF first, or choose a model file")
        return self.operator

    def run_deblur(self, *_) -> None:
        """Richardson-Lucy with the space-varying 3D PSF, in a worker."""
        layer = self.image.value
        try:
            stack, scale, translate = stack_of(layer)
            op = self.model()
            if stack.shape[1:] != op.image_shape[1:]:
                raise ValueError(f"z-stack: slices of {stack.shape[1:]}, the model acts on "
                                 f"{op.image_shape[1:]}")
        except (ValueError, OSError) as exc:
            self._fail(exc, self.deblur_task)
            return
        gen = iter_richardson_lucy_3d(stack, op, n_iter=int(self.iterations.value),
                                      stop=STOP_FIT if self.stop.value else None,
                                      accelerate=bool(self.accelerate.value),
                                      device=str(self.device.value))
        self.deblur_result.value = ""
        started = time.perf_counter()

        def on_progress(rec) -> None:
            line = estimate_line(rec)
            if line is not None:
                self.deblur_result.value = line

        def on_cancel() -> None:
            self.deblur_result.value = ""  # no estimate of a run that is not running

        def on_result(res) -> None:
            show_layers(self._viewer, deblurred_layers(res, layer, scale, translate),
                        step=DEBLUR_STEP, replace=True)
            show_step(self, STEP, layer)
            seconds = time.perf_counter() - started
            why = ("the result stopped changing" if res.stopped
                   else "the most iterations asked for")
            estimate = ("" if res.estimate_s is None
                        else f" (estimated {res.estimate_s:.0f} s)")
            self.deblur_result.value = (
                f"{res.iterations} Richardson-Lucy iterations ({why}) on the "
                f"{res.device.upper()}, {res.n_kernels:.1f} kernels a block; "
                f"{seconds:.0f} s{estimate}")

        self.deblur_task.run(gen, on_result, on_progress=on_progress, on_cancel=on_cancel)


__all__ = ["Volume3DWidget"]
