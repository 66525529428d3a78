"""npe2 readers: model files (``.npz``), TIFF images with their pixel size, and OME-Zarr
z-stacks (lazily, with their voxel size).

No napari import: readers return layer-data tuples.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable


def _single_path(path) -> str | None:
    if isinstance(path, (list, tuple)):
        if len(path) != 1:
            return None
        path = path[0]
    return os.fspath(path) if isinstance(path, (str, os.PathLike)) else None


def is_model_file(path: str | os.PathLike) -> bool:
    """True if ``path`` is a napari-psfspace model: an .npz whose header has our format."""
    import numpy as np

    from .core.model.operator_file import FORMAT_NAME

    try:
        with np.load(path, allow_pickle=False) as data:
            if "header" not in data.files:
                return False
            raw = data["header"]
            if raw.dtype != np.uint8 or raw.ndim != 1:
                return False
            header = json.loads(raw.tobytes().decode("utf-8"))
    except (OSError, ValueError, EOFError, UnicodeDecodeError, AttributeError, TypeError):
        return False
    return isinstance(header, dict) and header.get("format") == FORMAT_NAME


def get_model_reader(path) -> Callable | None:
    """npe2 reader contribution for model files; None for anything else."""
    p = _single_path(path)
    if p is None or not p.lower().endswith(".npz") or not is_model_file(p):
        return None
    return read_model


def read_model(path) -> list[tuple]:
    """Layer-data tuples of a model: PSF-grid mosaic, basis and coefficient-map mosaics.

    The layers get the model's pixel size (``metadata["pixel_size_um"]``) as scale when
    it is known; the PSF-grid layer carries the operator, so saving that layer as
    ``.npz`` writes the model back.
    """
    from ._layers import Frame, operator_layers
    from .core.model.operator import load_operator

    p = _single_path(path)
    op = load_operator(p)
    px = op.metadata.get("pixel_size_um")
    frame = Frame(op.image_shape, (px, px) if px else (1.0, 1.0), units="µm" if px else None)
    name = os.path.splitext(os.path.basename(p))[0]
    out = []
    for data, kwargs, kind in operator_layers(op, frame):
        kwargs = {**kwargs, "name": f"{kwargs['name']} [{name}]"}
        out.append((data, kwargs, kind))
    return out


def get_tiff_reader(path) -> Callable | None:
    """npe2 reader contribution: a 2-D or 3-D TIFF with its pixel size as scale."""
    p = _single_path(path)
    if p is None or not p.lower().endswith((".tif", ".tiff")) or not os.path.isfile(p):
        return None
    return read_tiff


def read_tiff(path) -> list[tuple]:
    """A TIFF as an image layer scaled in micrometres (z spacing for stacks).

    napari's builtin reader ignores the pixel size; this one reads it from the ImageJ
    metadata or the resolution tags (see :func:`napari_psfspace.io.read_image`).
    """
    from .io import read_array

    p = _single_path(path)
    data, info = read_array(p)
    px = info.pixel_size
    meta = {"pixel_size_um": px, "z_spacing_um": info.z_spacing}
    kwargs = {"name": os.path.splitext(os.path.basename(p))[0], "metadata": meta}
    if px:
        kwargs["scale"] = ((info.z_spacing or px, px, px) if data.ndim == 3 else (px, px))
        kwargs["units"] = ("µm",) * data.ndim  # napari's scale bar reads them
    return [(data, kwargs, "image")]


def get_ome_zarr_reader(path) -> Callable | None:
    """npe2 reader contribution: an OME-Zarr image folder (a z-stack of one channel);
    None for anything else, so that other readers (napari-ome-zarr) take the rest."""
    from .ome_zarr import is_ome_zarr

    p = _single_path(path)
    if p is None or not is_ome_zarr(p):
        return None
    return read_ome_zarr_layer


def read_ome_zarr_layer(path) -> list[tuple]:
    """An OME-Zarr z-stack as an image layer on a dask array (read a chunk at a time as
    napari shows it), scaled in micrometres from its metadata."""
    from .ome_zarr import read_ome_zarr

    p = _single_path(path)
    data, px, dz, _ = read_ome_zarr(p, lazy=True, complete=False)
    meta = {"pixel_size_um": px, "z_spacing_um": dz}
    kwargs = {"name": os.path.splitext(os.path.basename(p.rstrip("/\\")))[0],
              "metadata": meta}
    if px:
        kwargs["scale"] = (dz or px, px, px)[-data.ndim:]
        kwargs["units"] = ("µm",) * data.ndim
    return [(data, kwargs, "image")]
