"""Dock widget 5: learn the family of a microscope's operators from many bead images.

The images come from a z-stack layer (a range of its slices: each slice a condition),
from several 2-D image layers, or from a folder of TIFFs (read one at a time inside the
tasks). The work is :func:`~napari_psfspace.core.family.iter_estimate_family` in a
worker thread (dask's threaded scheduler inside it); the widget shows the PSF grid of
each image's operator under a slider, the PSF basis and the spatial maps as layers, and
the conditions as a table in the dock.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    PushButton,
    Select,
    SpinBox,
)
from napari.utils.notifications import show_error, show_info

from .._layers import SUB_GRID, Frame, axis_unit, family_layers, find_layer, show_layers
from ..core.common.progress import Progress
from ..core.family import OperatorFamily, iter_estimate_family
from ._view import show_step
from ._worker import (
    CoreTask,
    RadiusEdit,
    image_choices,
    pixel_size_of,
    result_text,
    show_rows,
    table_widget,
)

if TYPE_CHECKING:
    import napari

SOURCES = ("slices of a stack layer", "image layers", "folder of TIFFs")


def _plane(data, z: int | None) -> np.ndarray:
    """Loader of one plane of a layer's data (read in the task, not before)."""
    return np.array(data if z is None else data[z], copy=True)


def _learn_and_show(loaders, *, grid: int, **kwargs):
    """The family, then what the widget shows of it (all in the worker)."""
    sub = yield from iter_estimate_family(loaders, **kwargs)
    yield Progress("display", 1.0, f"PSF grids of {sub.n_images} images")
    ys, xs, psfs = sub.psf_grids(grid)
    return sub, ys, xs, psfs, sub.condition_coordinates(2)


#: The conditions table's columns: each image's label (its focus where known), its
#: place among the conditions (the first two coordinates of its operator in the
#: family), and its held-out residual.
CONDITION_COLUMNS = ("image", "place\n1", "place\n2", "held-\nout")


def conditions_table(sub: OperatorFamily, coords: np.ndarray) -> dict:
    """A magicgui Table's value: one row a condition (image) the family learnt from."""
    images = [int(i) for i in sub.metadata.get("images", range(sub.n_images))]
    labels = sub.metadata.get("labels") or [str(i) for i in images]
    held = sub.metadata.get("heldout") or []
    c = np.asarray(coords, float).reshape(len(images), -1)
    rows = []
    for k, label in enumerate(labels):
        # a stack slice's label ("stack[+0.40 µm]") in the table: what is in brackets
        short = label.rsplit("[", 1)[-1].rstrip("]") if label.endswith("]") else label
        h = held[k] if len(held) == len(images) else {}
        res = f"{h['residual_mean']:.3f}" if h.get("n_beads") else "-"
        rows.append([short, f"{c[k, 0]:+.2f}",
                     f"{c[k, 1]:+.2f}" if c.shape[1] > 1 else "-", res])
    return {"data": rows, "index": list(range(len(rows))), "columns": list(CONDITION_COLUMNS)}


def slice_label(layer, z: int) -> str:
    """What names slice ``z`` of a stack layer among the family's conditions: its focus
    in µm where the stack carries one per slice (``metadata["z_um"]``, as the focus
    series does), else its z position in µm where the stack is calibrated (a z scale
    other than 1), else its index."""
    focus = (layer.metadata or {}).get("z_um")
    if focus is not None and len(focus) == np.shape(layer.data)[0]:
        return f"{float(focus[z]):+.2f} µm"
    dz = float(layer.scale[0])
    if dz != 1.0:
        return f"z {float(layer.translate[0]) + z * dz:.2f} µm"
    return str(z)


class LearnFamilyWidget(Container):
    """Learn ``h_i``, ``a_j`` and one ``Gamma_k`` per image; show and save the family."""

    def __init__(self, viewer: napari.viewer.Viewer) -> None:
        self._viewer = viewer
        self.source = ComboBox(label="images from", choices=list(SOURCES))
        self.stack = ComboBox(label="stack", choices=self._stacks)
        self.first = SpinBox(label="first slice", min=0, max=100000, value=0)
        self.last = SpinBox(label="last slice", min=0, max=100000, value=0)
        self.last.tooltip = "Included. Each slice is one condition (e.g. one focus)."
        self.layers = Select(label="image layers", choices=self._planes, visible=False)
        self.folder = FileEdit(mode="d", label="folder", visible=False)
        self.radius = RadiusEdit()
        self.n_psf = SpinBox(label="PSFs (0: auto)", min=0, max=50, value=0)
        self.n_psf.tooltip = "PSFs in the family's basis (I in the paper); 0: from the data."
        self.n_space = SpinBox(label="spatial maps (0: auto)", min=0, max=64, value=0)
        self.n_space.tooltip = ("Spatial maps the family shares over the field (J in the "
                                "paper); 0: from the data.")
        self.holdout = CheckBox(value=True, text="judge each image on held-out beads")
        self.holdout.tooltip = ("A fifth of each image's beads, spread over the field, are "
                                "kept out of a first fit and judged against it (takes "
                                "about twice as long).")
        self.save_path = FileEdit(mode="w", filter="*.npz", label="save family to")
        self.save_path.tooltip = ("Optional: a file to save the family to when it is "
                                  "learnt (empty: nothing is written).")
        self.learn = PushButton(text="Learn family")
        self.task = CoreTask(self.learn)
        self.result = result_text()
        self.conditions = table_widget(
            CONDITION_COLUMNS, "conditions",
            "Each image the family learnt from, placed by the first two coordinates of its "
            "operator in the family: close places, close blurs.")
        super().__init__(widgets=[
            self.source, self.stack, self.first, self.last, self.layers, self.folder,
            self.radius, self.n_psf, self.n_space, self.holdout, self.save_path,
            self.learn, self.task, self.result, self.conditions])
        self.subspace: OperatorFamily | None = None
        self.source.changed.connect(self._on_source)
        self.stack.changed.connect(self._on_stack)
        self.learn.changed.connect(self.run)
        viewer.layers.events.inserted.connect(self._on_layers)
        viewer.layers.events.removed.connect(self._on_layers)
        self._on_source()
        self._on_stack()

    # ---------------------------------------------------------------- choices
    def _stacks(self, _widget=None) -> list:
        return image_choices(self._viewer, 3)()

    def _planes(self, _widget=None) -> list:
        return image_choices(self._viewer, 2)()

    def _on_layers(self, *_) -> None:
        self.reset_choices()
        # several 2-D images and no stack: they are the images
        if not self._stacks() and len(self._planes()) >= 2 and self.source.value == SOURCES[0]:
            self.source.value = SOURCES[1]

    def _on_source(self, *_) -> None:
        src = self.source.value
        for w in (self.stack, self.first, self.last):
            w.visible = src == SOURCES[0]
        self.layers.visible = src == SOURCES[1]
        self.folder.visible = src == SOURCES[2]

    def _on_stack(self, *_) -> None:
        layer = self.stack.value
        if layer is None:
            return
        n = int(np.shape(layer.data)[0])
        self.first.max = self.last.max = n - 1
        self.first.value, self.last.value = 0, n - 1
        meta = layer.metadata or {}
        self.radius.set_calibration(pixel_size_of(layer), meta.get("psf_radius"))

    # ---------------------------------------------------------------- inputs
    def _inputs(self) -> tuple[list, Frame, list[str], tuple[float, float]]:
        """Loaders, the frame the family is shown in, a label per image, and the world
        position and step of the images along a stack's first axis.

        Raises ValueError naming the widget's field when the choice cannot work.
        """
        src = self.source.value
        if src == SOURCES[0]:
            layer = self.stack.value
            if layer is None:
                raise ValueError("stack: open a z-stack (Z, Y, X) first; each slice is one "
                                 "condition")
            a, b = int(self.first.value), int(self.last.value)
            if b < a + 1:
                raise ValueError(f"last slice must be after first slice (at least 2 "
                                 f"slices), got first {a}, last {b}")
            data = layer.data
            frame = Frame(tuple(np.shape(data)[-2:]), tuple(np.asarray(layer.scale)[-2:]),
                          tuple(np.asarray(layer.translate)[-2:]), units=axis_unit(layer))
            z0, dz = float(layer.translate[0]), float(layer.scale[0])
            return ([functools.partial(_plane, data, z) for z in range(a, b + 1)], frame,
                    [f"{layer.name}[{slice_label(layer, z)}]" for z in range(a, b + 1)],
                    (z0 + a * dz, dz))
        if src == SOURCES[1]:
            chosen = list(self.layers.value)
            if len(chosen) < 2:
                raise ValueError(f"image layers: choose at least 2 (one per condition), "
                                 f"got {len(chosen)}")
            first = chosen[0]
            frame = Frame(tuple(np.shape(first.data)), tuple(np.asarray(first.scale)),
                          tuple(np.asarray(first.translate)), units=axis_unit(first))
            return ([functools.partial(_plane, c.data, None) for c in chosen], frame,
                    [c.name for c in chosen], (0.0, 1.0))
        from ..io import stack_loaders

        folder = str(self.folder.value)
        if folder in ("", "."):
            raise ValueError("folder: choose a folder of TIFFs (one image per condition)")
        loaders, labels = stack_loaders([folder])
        shape = np.shape(loaders[0]()) if loaders else (1, 1)
        return loaders, Frame(tuple(shape[-2:])), labels, (0.0, 1.0)

    def _input_layer(self):
        """The layer the family was learnt from, shown beside its results (None for a
        folder)."""
        if self.source.value == SOURCES[0]:
            return self.stack.value
        if self.source.value == SOURCES[1]:
            return next(iter(self.layers.value), None)
        return None

    # ---------------------------------------------------------------- run
    def run(self, *_) -> None:
        """Learn the family in a worker thread; show and save it when done."""
        try:
            loaders, frame, labels, axis = self._inputs()
        except ValueError as exc:
            show_error(str(exc))
            self.task.status.value = str(exc)
            return
        path = Path(self.save_path.value) if str(self.save_path.value) not in ("", ".") else None
        n_psf = int(self.n_psf.value) or None
        n_space = int(self.n_space.value) or None
        # images read a core's worth at a time: the bar moves (and Cancel is honoured)
        # after each few images, not after the first 8
        gen = _learn_and_show(loaders, grid=6, psf_radius=self.radius.pixels, n_psf=n_psf,
                              n_space=n_space, holdout=0.2 if self.holdout.value else None,
                              chunk=max(1, os.cpu_count() or 1))

        def on_result(got) -> None:
            sub, ys, xs, psfs, coords = got
            sub.metadata["labels"] = [labels[i] for i in sub.metadata.get("images", [])]
            self.subspace = sub
            show_layers(self._viewer, family_layers(sub, ys, xs, psfs, frame,
                                                      stack_axis=axis),
                        step="Family", replace=True)
            self._viewer.layers.selection.active = find_layer(self._viewer, SUB_GRID)
            show_rows(self.conditions, conditions_table(sub, coords))
            show_step(self, "Family", self._input_layer())
            self.result.value = self._describe(sub)
            if path is not None:
                sub.save(path)
                show_info(f"Family saved to {path}")
                self.result.value += f"\nsaved to {path}"

        self.task.run(gen, on_result)

    @staticmethod
    def _describe(sub: OperatorFamily) -> str:
        meta = sub.metadata
        beads = meta.get("beads_per_image", [])
        text = (f"{sub.n_psf} PSFs in the basis, {sub.n_space} spatial maps, from "
                f"{sub.n_images} images ({sum(beads)} beads, {min(beads, default=0)}-"
                f"{max(beads, default=0)} per image)")
        skipped = meta.get("skipped") or {}
        if skipped:
            text += f"\nskipped (no usable bead): images {', '.join(sorted(skipped))}"
        held = [h for h in (meta.get("heldout") or []) if h.get("n_beads")]
        if held:
            res = np.array([h["residual_mean"] for h in held])
            floor = np.array([h["noise_floor_mean"] for h in held])
            # the held-out split that chose each image's blend (relative l2 per bead), not
            # the held-out error of one image (Model and Diagnose give that)
            text += (f"\nblend chosen on held-out beads: their relative residual "
                     f"{res.mean():.3f} (images {res.min():.3f}-{res.max():.3f}; noise "
                     f"{floor.mean():.3f})")
        return text
