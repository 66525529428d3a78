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

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import ComboBox, Container, FileEdit, Label, PushButton, SpinBox
from napari.layers import Image
from napari.utils.notifications import show_error

from ..core.common.measures import in_units, psf_measures
from ..core.common.progress import Progress
from ..core.volume import iter_estimate_operator_3d, load_operator_3d
from ..core.volume.deconvolve3d import iter_richardson_lucy_3d
from ..core.volume.measures import measure_maps
from ..core.volume.views import psf_grid_3d
from ._layers import COLORBAR, show_layers
from ._worker import CoreTask, result_text

if TYPE_CHECKING:
    import napari

STEP = "3D"
PSF_GRID_3D = "3D PSF grid"
PSF_SECTIONS = "3D PSF grid: sections (z down, x across)"
PSF_SECTIONS_Y = "3D PSF grid: sections (z down, y across)"
DEBLURRED_3D = "deblurred 3D"
OPERATOR_3D_KEY = "psfspace_operator_3d"
#: (measure, layer name without its unit, colormap) of the maps shown; the unit (nm where
#: the stack's voxel size is known, else px and planes) is added to the name.
MAPS = (("focal_plane", "focal shift", "coolwarm"),
        ("fwhm_lateral", "lateral FWHM", "viridis"),
        ("fwhm_axial", "axial FWHM", "viridis"),
        ("astigmatic_split", "astigmatic split", "PiYG"))


def map_in_units(key: str, values: np.ndarray, plane: int, voxel) -> tuple[np.ndarray, str]:
    """A measure map as shown: the focal shift from the bead plane; nm where ``voxel``
    ``(dz, dy, dx)`` in µm is known, else px and planes. Returns the map and its unit."""
    m = values.astype(np.float64) - (plane if key == "focal_plane" else 0.0)
    if voxel is None:
        return m.astype(np.float32), "px" if key == "fwhm_lateral" else "planes"
    step = voxel[1] if key == "fwhm_lateral" else voxel[0]
    return (m * step * 1000.0).astype(np.float32), "nm"


def stack_of(layer) -> tuple[np.ndarray, tuple, tuple]:
    """A z-stack layer's data (a copy for the worker), scale and translate (z, y, x);
    ValueError naming the layer unless it is one."""
    if layer is None:
        raise ValueError("image: open a z-stack (Z, Y, X) first")
    if getattr(layer, "rgb", False) or np.ndim(layer.data) != 3:
        raise ValueError(f"image: layer {layer.name!r} has shape {np.shape(layer.data)}; "
                         f"a z-stack (Z, Y, X) is expected")
    return (np.array(layer.data, copy=True), tuple(float(s) for s in layer.scale),
            tuple(float(t) for t in layer.translate))


def _learn(stack, voxel, **kwargs):
    """Estimate, then the views (in the worker)."""
    est = yield from iter_estimate_operator_3d(stack, voxel_size=voxel, **kwargs)
    yield Progress("views", 1.0, "PSF grid and maps")
    grid = psf_grid_3d(est.operator, 5)
    maps = measure_maps(est.operator, 8, 8)
    _, h, w = est.operator.shape
    centre = psf_measures(est.operator.psf_at((h - 1) / 2, (w - 1) / 2))
    return est, grid, maps, in_units(centre, voxel)


class Volume3DWidget(Container):
    """Learn a space-varying 3D PSF from a bead z-stack; deblur a z-stack with it."""

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self._viewer = viewer
        self.image = ComboBox(label="z-stack", choices=self._stacks)
        self.radius = SpinBox(label="PSF radius (px)", min=2, max=500, value=16)
        self.radius.tooltip = "Lateral radius of the 3D PSF, pixels (the widest plane kept)."
        self.z_radius = SpinBox(label="z radius (planes)", min=0, max=1000, value=0)
        self.z_radius.tooltip = "Planes kept on each side of the bead plane (0: all)."
        self.n_psf = SpinBox(label="basis size I", min=0, max=50, value=0)
        self.n_psf.tooltip = "Number of 3D kernels (0: chosen from the data)."
        self.learn = PushButton(text="Learn 3D PSF")
        self.learn_task = CoreTask(self.learn)
        self.learn_result = result_text(6)
        self.model_file = FileEdit(mode="r", filter="*.npz", label="or model file")
        self.iterations = SpinBox(label="iterations", min=1, max=10000, value=50)
        self.deblur = PushButton(text="Deblur 3D")
        self.deblur_task = CoreTask(self.deblur)
        self.deblur_result = Label(value="")
        super().__init__(widgets=[
            self.image, self.radius, self.z_radius, self.n_psf, self.learn,
            self.learn_task, self.learn_result, self.model_file, self.iterations,
            self.deblur, self.deblur_task, self.deblur_result])
        self.operator = None
        self.learn.changed.connect(self.run_learn)
        self.deblur.changed.connect(self.run_deblur)
        viewer.layers.events.inserted.connect(lambda *_: self.reset_choices())
        viewer.layers.events.removed.connect(lambda *_: self.reset_choices())

    def _stacks(self, _widget=None) -> list:
        return [(layer.name, layer) for layer in self._viewer.layers
                if isinstance(layer, Image) and np.ndim(layer.data) == 3
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
        gen = _learn(stack, voxel, psf_radius=float(self.radius.value),
                     z_radius=int(self.z_radius.value) or None,
                     n_psf=int(self.n_psf.value) or None)

        def on_result(got) -> None:
            est, (_, _, volume, sections, sections_y), (_, _, maps), (c, u) = got
            self.operator = op = est.operator
            self._show(op, volume, (sections, sections_y), maps, scale, translate)
            meta = op.metadata
            self.learn_result.value = (
                f"I = {op.n_psf} 3D kernels of {'x'.join(map(str, op.kernel_shape))} from "
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

    def _show(self, op, volume, sections, maps, scale, translate) -> None:
        dz, dy, dx = scale
        tz, ty, tx = translate
        _, h, w = op.shape
        k, p, _ = op.kernel_shape
        gap = 0.05 * w * dx
        left = tx + w * dx + gap  # beside the stack
        tiles = volume.shape[1]
        s = h * dy / tiles  # the grid as tall as the field
        z0 = tz + (op.plane - k // 2) * dz  # its bead plane on the stack's
        tuples = [
            (volume, {"name": PSF_GRID_3D, "scale": (dz, s, s), "translate": (z0, ty, left),
                      "colormap": "magma",
                      "metadata": {OPERATOR_3D_KEY: op,
                                   "about": "3D PSF at 5 x 5 field positions, each scaled "
                                            "to its maximum, gamma 0.5"}}, "image"),
            (sections[0], {"name": PSF_SECTIONS,
                           "scale": (dz * s / dy, s), "translate": (ty + h * dy + gap, left),
                           "colormap": "magma"}, "image"),
            (sections[1], {"name": PSF_SECTIONS_Y, "scale": (dz * s / dy, s),
                           "translate": (ty + h * dy + gap,
                                         left + sections[1].shape[1] * s + gap),
                           "colormap": "magma"}, "image"),
        ]
        voxel = None if np.allclose(scale, 1.0) else scale
        for j, (key, label, cmap) in enumerate(MAPS):
            m, unit = map_in_units(key, maps[key], op.plane, voxel)
            name = f"{label} ({unit})"
            finite = m[np.isfinite(m)]
            lim = ((float(finite.min()), float(finite.max())) if finite.size
                   else (0.0, 1.0))
            if lim[1] - lim[0] < 1e-3 * max(abs(lim[0]), abs(lim[1]), 1.0):
                # a flat map (one PSF for the field): its value mid-bar, not 0-1000
                pad = 0.05 * max(abs(lim[0]), 1.0)
                lim = (lim[0] - pad, lim[1] + pad)
            if key in ("focal_plane", "astigmatic_split") and finite.size:
                top = max(abs(lim[0]), abs(lim[1]), 1e-6)
                lim = (-top, top)
            # a 2 x 2 block of half-size maps below the stack
            ms = (h * dy / 2 / m.shape[0], w * dx / 2 / m.shape[1])
            row, col = divmod(j, 2)
            tuples.append((np.nan_to_num(m, nan=0.0),
                           {"name": name, "scale": ms,
                            "translate": (ty + h * dy + gap + row * (h * dy / 2 + gap / 2),
                                          tx + col * (w * dx / 2 + gap / 2)),
                            "colormap": cmap, "contrast_limits": lim, COLORBAR: True},
                           "image"))
        show_layers(self._viewer, tuples, step=STEP, replace=True)

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
            if stack.shape[1:] != op.shape[1:]:
                raise ValueError(f"z-stack: slices of {stack.shape[1:]}, the model acts on "
                                 f"{op.shape[1:]}")
        except (ValueError, OSError) as exc:
            self._fail(exc, self.deblur_task)
            return
        gen = iter_richardson_lucy_3d(stack, op, n_iter=int(self.iterations.value))

        def on_result(res) -> None:
            show_layers(self._viewer, [(res.volume, {
                "name": DEBLURRED_3D, "scale": scale, "translate": translate,
                "colormap": "magma", "blending": "additive",
                "metadata": {"source": layer.name, "iterations": res.iterations,
                             "background": res.background}}, "image")], step="3D deblur",
                replace=True)
            self.deblur_result.value = (f"{res.iterations} Richardson-Lucy iterations, "
                                        f"{res.n_kernels:.1f} kernels a block")

        self.deblur_task.run(gen, on_result)


__all__ = ["Volume3DWidget"]
