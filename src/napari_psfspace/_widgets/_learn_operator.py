"""Dock widget 3: learn the product-convolution operator, show it, save it."""

from __future__ import annotations

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
from napari.utils.notifications import show_info

from .._layers import (
    PSF_GRID,
    bead_fwhm_layer,
    beads_layer,
    find_layer,
    heldout_layers,
    operator_layers,
    psf_layers,
    set_statuses,
    show_layers,
    user_beads,
)
from ..core.common.measures import field_fwhm, fwhm_line, patch_fwhms
from ..core.diagnosis.loop import iter_heldout_error
from ..core.diagnosis.metric import line as heldout_line
from ..core.model.estimate import iter_estimate
from ..core.model.fewbeads import one_psf_note
from ..core.model.operator import ProductConvolution
from ..report import model_lines
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

N_PSF_MODES = {"auto (held-out beads)": None, "auto (rank rule)": "rule", "fixed": "fixed"}


def _learn(plane, frame, source: str, **kwargs):
    """iter_estimate, then the held-out error (the one accuracy figure, by the code
    Diagnose uses: the same number for the same beads), then stamp the image's pixel
    size and name on the model."""
    est = yield from iter_estimate(plane, **kwargs)
    n_psf = kwargs.get("n_psf")
    try:
        held = yield from iter_heldout_error(
            plane, psf_radius=kwargs["psf_radius"], threshold=kwargs["threshold"],
            n_psf=n_psf if isinstance(n_psf, int) else None,
            smoothing=kwargs.get("smoothing"), bead_diameter=kwargs.get("bead_diameter", 0.0),
            beads=kwargs.get("beads"))
    except ValueError as exc:  # e.g. too few beads to judge each by the others
        held = str(exc)
    op = est.operator
    meta = {**op.metadata, "pixel_size_um": frame.pixel_size, "image": source,
            "heldout_error": held if isinstance(held, str) else held.to_dict()}
    est.operator = ProductConvolution(op.basis, op.coefficients, shape=op.image_shape,
                                      grid=op.grid, metadata=meta)
    if one_psf_note(meta):  # no field map: the beads' own FWHMs show the field instead
        est.info["bead_fwhm"] = (np.asarray(est.patches.centers, float),
                                 patch_fwhms(est.patches.psf))
    return est


#: Screen pixels the basis-size table takes at most in the dock, and its columns.
SIZES_HEIGHT = 220
SIZE_COLUMNS = ("PSFs", "held-out\nerror", "")


def sizes_table(meta: dict) -> dict:
    """A magicgui Table's value: the held-out error of each PSF basis size tried
    (``meta["heldout_error_by_n_psf"]``, sizes 1..), the chosen one marked."""
    errors = meta.get("heldout_error_by_n_psf") or []
    chosen = meta.get("n_psf")
    rows = [[str(k), f"{e:.4g}", "chosen" if k == chosen else ""]
            for k, e in enumerate(errors, start=1)]
    return {"data": rows, "index": list(range(len(rows))), "columns": list(SIZE_COLUMNS)}


class LearnOperatorWidget(FollowsBeads, Container):
    """Learn the space-varying PSF from the beads of a Points layer and save the model.

    Shows the PSF basis ``h_i`` (a stack), the coefficient maps ``alpha_i`` (a stack
    over the image, hidden at first), a mosaic of the PSF at 8x8 field positions and the
    held-out residual of each held-out bead.
    """

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self._viewer = viewer
        self.image = ComboBox(label="image", choices=image_choices(viewer))
        self.points = ComboBox(label="beads", choices=bead_layer_choices(viewer, allow_none=True))
        self.radius = RadiusEdit()
        self.threshold = FloatSpinBox(value=8.0, min=0.5, max=1000.0, step=0.5,
                                      label="threshold", visible=False)
        self.n_psf_mode = ComboBox(label="PSF basis size", choices=list(N_PSF_MODES))
        self.n_psf_mode.tooltip = ("How many PSFs the basis holds (I in the paper): chosen "
                                   "from the data, or fixed.")
        self.n_psf = SpinBox(value=4, min=1, max=50, label="PSFs", visible=False)
        self.auto_smoothing = CheckBox(value=True, text="automatic smoothing")
        self.smoothing = FloatSpinBox(value=1e-3, min=0.0, max=1e6, step=1e-3,
                                      label="smoothing", visible=False)
        self.smoothing.tooltip = "Thin-plate smoothing eta (0 interpolates the beads)."
        self.remove_motion = CheckBox(value=False, text="remove motion blur")
        self.remove_motion.tooltip = (
            "Motion blur (a smear common to all beads) is always looked for and reported. "
            "Tick to divide it out of the model: a calibration of the optics alone, for "
            "when the sample was still.")
        self.save_path = FileEdit(mode="w", filter="*.npz", label="save model to")
        self.save_path.tooltip = ("Optional: a file to save the model to when it is learnt "
                                  "(empty: nothing is written; File > Save Selected Layers "
                                  "saves it later).")
        self.learn = PushButton(text="Learn operator")
        self.task = CoreTask(self.learn)
        self.result = result_text()
        self.sizes = table_widget(
            SIZE_COLUMNS, "basis size",
            "The held-out error of each PSF basis size tried (the relative residual "
            "energy of beads kept out of the fit): the size is chosen where it stops "
            "falling.")
        self.sizes.native.setMaximumHeight(SIZES_HEIGHT)  # scrolls past a dozen sizes
        self.psf_y = FloatSpinBox(label="PSF at y", min=0.0, max=1e4, step=0.1)
        self.psf_x = FloatSpinBox(label="PSF at x", min=0.0, max=1e4, step=0.1)
        self.psf_unit = Label(value="position in pixels")
        self.psf_unit.tooltip = "The same unit as the PSF radius."
        self.show_psf = PushButton(text="Show PSF at this position", enabled=False)
        super().__init__(widgets=[
            self.image, self.points, self.radius, self.threshold, self.n_psf_mode,
            self.n_psf, self.auto_smoothing, self.smoothing, self.remove_motion,
            self.save_path, self.learn,
            self.task, self.result, self.sizes, self.psf_unit, self.psf_y, self.psf_x,
            self.show_psf])
        self.operator: ProductConvolution | None = None
        self._frame = None
        self.n_psf_mode.changed.connect(
            lambda v: setattr(self.n_psf, "visible", v == "fixed"))
        self.auto_smoothing.changed.connect(
            lambda v: setattr(self.smoothing, "visible", not v))
        self.learn.changed.connect(self.run)
        self.show_psf.changed.connect(self.psf_here)
        self._connect_inputs(viewer, self._on_inputs)

    def _on_inputs(self, *_) -> None:
        img, pts = self.image.value, self.points.value
        self._follow(pts)
        self.threshold.visible = pts is None
        if img is None:
            return
        self._calibrate(img, pts)
        h, w = img.data.shape[-2:]
        # the position in the radius's unit: um when the image has a pixel size
        px = self.radius.pixel_size
        self._psf_unit = px or 1.0
        self.psf_unit.value = "position in µm" if px else "position in pixels"
        self.psf_unit.tooltip = (f"The same unit as the PSF radius ({px:g} µm a pixel)."
                                 if px else "The same unit as the PSF radius.")
        self.psf_y.max = round((h - 1) * self._psf_unit, 2)
        self.psf_x.max = round((w - 1) * self._psf_unit, 2)
        self.psf_y.value = round((h - 1) / 2 * self._psf_unit, 2)
        self.psf_x.value = round((w - 1) / 2 * self._psf_unit, 2)

    def run(self, *_) -> None:
        """Learn the operator in a worker thread; show and save it when done."""
        img, pts = self.image.value, self.points.value
        got = self._bead_plane(img, pts)
        if got is None:
            return
        plane, frame = got
        beads, ids = None, None
        if pts is not None:
            beads, ids = user_beads(self._viewer, pts, frame)
        mode = N_PSF_MODES[self.n_psf_mode.value]
        n_psf = int(self.n_psf.value) if mode == "fixed" else mode
        smoothing = None if self.auto_smoothing.value else float(self.smoothing.value)
        path = Path(self.save_path.value) if str(self.save_path.value) not in ("", ".") else None
        r = self.radius.pixels
        gen = _learn(plane, frame, img.name, psf_radius=r, n_psf=n_psf, smoothing=smoothing,
                     threshold=float(self.threshold.value), beads=beads,
                     bead_diameter=self._bead_diameter_px(),
                     remove_motion=bool(self.remove_motion.value))

        def on_result(est) -> None:
            self.operator, self._frame = est.operator, frame
            if pts is None:
                show_layers(self._viewer, [beads_layer(est.beads, frame, r)], step="Beads")
            else:
                set_statuses(pts, ids, est.beads.status)
            tuples = operator_layers(est.operator, frame)
            if est.heldout is not None and len(est.heldout.residual):
                tuples.extend(heldout_layers(est.heldout, frame))
            if "bead_fwhm" in est.info:
                tuples.append(bead_fwhm_layer(*est.info["bead_fwhm"], frame))
            show_layers(self._viewer, tuples, step="Model", replace=True)
            self._viewer.layers.selection.active = find_layer(self._viewer, PSF_GRID)
            show_step(self, "Model", img)
            show_rows(self.sizes, sizes_table(est.operator.metadata))
            self.show_psf.enabled = True
            self.result.value = self._describe(est, self.radius.pixel_size)
            if path is not None:
                est.operator.save(path)
                show_info(f"Model saved to {path}")
                self.result.value += f"\nsaved to {path}"

        self.task.run(gen, on_result)

    @staticmethod
    def _describe(est, pixel_size: float | None = None) -> str:
        meta = est.operator.metadata
        text = (f"basis of {meta['n_psf']} PSFs from {meta['n_beads_used']} beads\n"
                f"{est.beads.summary()}")
        h = meta.get("heldout_error")
        if isinstance(h, dict):
            text += "\n" + heldout_line(h["error"], h["noise_floor"], h["n_beads"])
        elif h:
            text += f"\nheld-out error not measured: {h}"
        for line in model_lines(meta, markdown=False):
            text += f"\n{line}"
        return text + "\n" + fwhm_line(field_fwhm(est.operator), pixel_size,
                                     one_psf=one_psf_note(est.operator.metadata))

    def psf_here(self, *_) -> None:
        """Show the PSF at (y, x) as a layer (File > Save Layer... writes a TIFF); the
        position is in micrometres when the image has a pixel size, as the radius is."""
        if self.operator is None:
            return
        unit = getattr(self, "_psf_unit", 1.0)  # um per px, or 1 (px)
        y, x = float(self.psf_y.value) / unit, float(self.psf_x.value) / unit
        try:
            psf = self.operator.psf_at(y, x)
        except ValueError as exc:
            from napari.utils.notifications import show_error

            show_error(str(exc))
            return
        show_layers(self._viewer, psf_layers(psf, y, x, self._frame), step="Model")
        show_step(self, "Model", self.image.value)
