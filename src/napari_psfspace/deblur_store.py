"""Deblurring a z-stack larger than memory: from a TIFF or OME-Zarr file to an OME-Zarr
(or TIFF), tile by tile, resumable.

The stack is read lazily (:func:`~napari_psfspace.io.read_stack`), deblurred by
Richardson-Lucy on tiles that exchange their margins every iteration
(:mod:`~napari_psfspace.core.volume.exchange3d`: the whole volume's result), with the
iterates in a work folder beside the output (``OUTPUT.iterates``) and the tile size from
a memory budget. An interrupted run leaves the work folder's last finished iteration and
the output's whole chunks; ``resume=True`` continues from them. The work folder is
removed once the output is complete.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass

import numpy as np

from .core.common.progress import Progress
from .core.common.threads import map_threads
from .core.common.twins import drained
from .core.volume.blocks3d import BLOCK, RTOL
from .core.volume.deconvolve3d import TINY, stack_statistics
from .core.volume.exchange3d import iter_richardson_lucy_3d_exchange, plan_for_memory
from .core.volume.operator3d import ProductConvolution3D


@dataclass
class StoreRun:
    """What :func:`deblur_to_store` did: the tile size, the iterations, the output's
    chunks written by this run (a resumed run writes only the missing ones), the device
    the tiles ran on (the local one's name)."""

    tile: int
    iterations: int
    chunks_written: int
    chunks_total: int
    background: float | None
    device: str = "cpu"


def is_zarr_path(path: str | os.PathLike) -> bool:
    """Whether an output path names an OME-Zarr folder (``.zarr``)."""
    return os.fspath(path).rstrip("/\\").lower().endswith(".zarr")


#: Largest relative difference between the stack's voxel size and the model's that is
#: taken as the same sampling: far above the rounding of a file's metadata (a TIFF's
#: rational resolution, a decimal z step), far below a change of objective or binning.
VOXEL_RTOL = 0.01


def stack_voxel_size(operator: ProductConvolution3D, info, *,
                     voxel_size: tuple[float, float, float] | None = None,
                     name: str = "the stack") -> tuple[float, float, float] | None:
    """The voxel size ``(dz, dy, dx)`` (µm) a stack is deblurred at, checked against the
    model's.

    Parameters
    ----------
    operator : ProductConvolution3D
    info : StackInfo
        The file's sampling (:func:`~napari_psfspace.io.read_stack`).
    voxel_size : (float, float, float), optional
        Given by the user; replaces the file's (each entry None keeps the file's).
    name : str
        The stack, as the error messages name it.

    Returns
    -------
    (float, float, float) or None
        None where neither the model nor the stack has one (both in pixels and planes).

    Raises
    ------
    ValueError
        The model has a voxel size and the stack neither has one nor is given one, or the
        two differ by more than :data:`VOXEL_RTOL`.
    """
    given = (None, None, None) if voxel_size is None else tuple(voxel_size)
    if len(given) != 3:
        raise ValueError(f"`voxel_size` must be (dz, dy, dx) in µm, got {voxel_size!r}")
    for v in given:
        if v is not None and not (np.isfinite(v) and v > 0):
            raise ValueError(f"`voxel_size` must hold positive µm, got {voxel_size!r}")
    dz = given[0] or getattr(info, "z_spacing", None)
    dy = given[1] or getattr(info, "pixel_size", None)
    dx = given[2] or getattr(info, "pixel_size", None)
    voxel = (dz, dy, dx) if dz and dy and dx else None
    model = operator.voxel_size
    if model is None:
        return voxel
    want = ", ".join(f"{v * 1000:.4g}" for v in model)
    if voxel is None:
        missing = [w for w, v in (("pixel size", dy), ("z step", dz)) if not v]
        raise ValueError(f"{name} gives no {' and no '.join(missing)}, and the model was "
                         f"learnt at {want} nm (dz, dy, dx): give the stack's "
                         "(--pixel-size-nm and --z-step-nm, or voxel_size=)")
    if not np.allclose(voxel, model, rtol=VOXEL_RTOL, atol=0):
        have = ", ".join(f"{v * 1000:.4g}" for v in voxel)
        raise ValueError(f"{name} is sampled at {have} nm (dz, dy, dx), the model at {want} "
                         "nm: deblur with a model learnt at the stack's sampling")
    return voxel


#: float32 volumes a run writes: the stack, H^T 1, the ratio and two iterates in the work
#: folder, and the output.
DISK_VOLUMES = 6


def _writable(path: str) -> bool:
    """Whether a file, or a folder and every folder and file in it, may be written."""
    from pathlib import Path

    from .io import file_writable, folder_writable

    if not os.path.isdir(path):
        return file_writable(Path(path))
    for folder, _, files in os.walk(path):
        if not folder_writable(Path(folder)) or not all(
                file_writable(Path(folder, f)) for f in files):
            return False
    return True


def _check_resumed_output(out: str, shape: tuple[int, int, int], tile: int) -> None:
    """One line where an OME-Zarr output to resume is not the one this run writes: its
    shape, dtype and chunks (one plane and one tile wide, so that each lies in one tile)."""
    from .ome_zarr import open_ome_zarr_output

    arr = open_ome_zarr_output(out)
    want = (1, min(tile, shape[1]), min(tile, shape[2]))
    if tuple(arr.shape) != shape:
        raise ValueError(f"cannot resume into {out!r}: it holds {tuple(arr.shape)} voxels, "
                         f"the stack {shape}")
    if np.dtype(arr.dtype) != np.float32:
        raise ValueError(f"cannot resume into {out!r}: it holds {arr.dtype}, this run "
                         "writes float32")
    if tuple(arr.chunks) != want:
        raise ValueError(f"cannot resume into {out!r}: its chunks are {tuple(arr.chunks)}, "
                         f"not {want} (one plane of one {tile} px tile): the chunks must "
                         "divide the tiles")


def work_folder(output: str | os.PathLike) -> str:
    """The folder of a run's iterates, beside its output."""
    return os.fspath(output).rstrip("/\\") + ".iterates"


def iter_deblur_to_store(stack_path: str | os.PathLike, operator: ProductConvolution3D,
                         output: str | os.PathLike, *, n_iter: int = 50,
                         memory: float | None = None, tile: int | None = None,
                         background: float | None = None, rtol: float = RTOL,
                         block: int = BLOCK, resume: bool = False, client=None,
                         workers: int | None = None,
                         voxel_size: tuple[float, float, float] | None = None,
                         device="cpu"):
    """Deblur a z-stack file into an OME-Zarr (``.zarr``) or TIFF output, tile by tile.

    Parameters
    ----------
    stack_path : str or PathLike
        TIFF or OME-Zarr z-stack (Z, Y, X) of the model's lateral size; read lazily.
    operator : ProductConvolution3D
    output : str or PathLike
        ``.zarr``: an OME-Zarr image (NGFF 0.4, float32, chunked by plane, the input's
        voxel size); else a TIFF (the result must then fit in memory).
    n_iter : int
        Richardson-Lucy iterations.
    memory : float, optional
        Bytes the run may hold at once; the tile size follows
        (:func:`~napari_psfspace.core.volume.exchange3d.plan_for_memory`: fewer tiles at
        once where one each would not fit).
    tile : int, optional
        Lateral tile size, pixels, instead of ``memory`` (default four blocks).
    background, rtol, block
        As :func:`~napari_psfspace.core.volume.exchange3d.richardson_lucy_3d_exchange`.
    resume : bool
        Finish an interrupted run of the same output (its iterates beside it).
    client : dask.distributed.Client, optional
        Runs the tiles on this cluster.
    workers : int, optional
        Tiles at once (the memory budget's divisor); default the machine's cores.
    voxel_size : (float, float, float), optional
        The stack's voxel size (dz, dy, dx), µm, where its file gives none or a wrong one;
        checked against the model's (:func:`stack_voxel_size`) and written with the output.
    device : {"cpu", "gpu", "auto"} or ArrayModule
        Where the tiles' blocks run (as
        :func:`~napari_psfspace.core.volume.exchange3d.richardson_lucy_3d_exchange`).

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    StoreRun
    """
    from .io import read_stack

    out, work, parent = _check_paths(output, resume)
    from .core.common.device import array_module

    am = array_module(device)  # "gpu" without one: one line, before any work
    stack, info = read_stack(stack_path, lazy=True)
    if tuple(stack.shape[1:]) != tuple(operator.image_shape[1:]):
        raise ValueError(f"the stack has slices of {tuple(stack.shape[1:])}, the model acts "
                         f"on {tuple(operator.image_shape[1:])}")
    voxel = stack_voxel_size(operator, info, voxel_size=voxel_size,
                             name=f"the stack {os.fspath(stack_path)!r}")
    depth = int(stack.shape[0])
    if tile is None and memory is not None:
        tile, workers = plan_for_memory(operator, depth, memory, block=block,
                                        workers=workers)
    tile = 4 * block if tile is None else tile
    _check_run(stack, stack_path, out, work, tile, resume)
    start, background = _starting_point(background, resume, out, parent, stack)
    os.makedirs(work, exist_ok=True)
    final = None
    last_by_this_run = not resume or _iterations_done(work) < n_iter
    if is_zarr_path(out):  # the last iteration writes its tiles into it as it makes them
        from .ome_zarr import create_ome_zarr

        if not os.path.isdir(out):
            create_ome_zarr(out, tuple(stack.shape), voxel_size=voxel, chunk=tile)
        final = os.path.join(out, "0")
    u = yield from iter_richardson_lucy_3d_exchange(
        stack, operator, n_iter=n_iter, background=background,
        start=start, tile=tile, block=block,
        rtol=rtol, store=work, resume=resume, client=client, workers=workers,
        device=device, output=final)
    yield Progress("write", 1.0, f"writing {out}")
    written, total = _write_output(u, out, tuple(stack.shape), info, voxel, n_iter=n_iter,
                                   tile=tile, resume=resume, workers=workers)
    if final is not None and last_by_this_run:
        written = total  # the last iteration wrote every chunk
    shutil.rmtree(work, ignore_errors=True)
    return StoreRun(tile, n_iter, written, total, background, am.name)


def _iterations_done(work: str) -> int:
    """The iterations an interrupted run's ``state.json`` says are done (0 where it has
    none or cannot be read: the iterations' own check then says why in one line)."""
    import json

    try:
        with open(os.path.join(work, "state.json"), encoding="utf-8") as f:
            return int(json.load(f)["done"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def _check_paths(output, resume):
    """The output and its work folder: the parent folder exists and is writable, a resume
    has an interrupted run to finish and a new run overwrites nothing."""
    out = os.fspath(output)
    work = work_folder(out)
    parent = os.path.dirname(os.path.abspath(out.rstrip("/\\")))
    if not os.path.isdir(parent):
        raise ValueError(f"cannot write {out}: the folder {parent} does not exist")
    from pathlib import Path

    from .io import folder_writable

    if not folder_writable(Path(parent)):
        raise ValueError(f"cannot write {out}: the folder {parent} is not writable")
    zarr_out = is_zarr_path(out)
    if resume and not os.path.isdir(work):
        if zarr_out and os.path.isdir(out):
            raise ValueError(f"nothing to resume for {out!r}: it is complete (no "
                             f"{os.path.basename(work)!r} beside it)")
        raise ValueError(f"nothing to resume for {out!r}: no {os.path.basename(work)!r} "
                         "beside it (run without --resume)")
    if not resume:
        for p in (out, work):
            if os.path.exists(p) and (zarr_out or p == work):
                raise ValueError(f"{p!r} exists: remove it, or give --resume to finish "
                                 "an interrupted run")
    return out, work, parent


def _starting_point(background, resume, out, parent, stack):
    """The background and the start, from the stack's statistics (a resumed run takes them
    from its state), and room on disk for the iterates and the output; before anything is
    written."""
    start = None  # a resumed run takes its background and start from its state
    if not resume:  # the stack's range and the background, before anything is written
        background, mean = stack_statistics(stack, background)  # read once, passed on
        start = max(mean - background, TINY)
        # the iterates' arrays and the output
        need = DISK_VOLUMES * 4.0 * float(np.prod(stack.shape))
        free = shutil.disk_usage(parent).free
        if need > free:
            raise ValueError(f"cannot write {out}: the run needs about {need / 1e9:.3g} GB "
                             f"on disk beside it ({DISK_VOLUMES} float32 volumes: the "
                             f"iterates and the output), {free / 1e9:.3g} GB are free")
    return start, background


def _check_run(stack, stack_path, out, work, tile, resume):
    """A resumed run can write where the interrupted one did, into an output of its
    stack's shape and tiles; the stack holds intensities."""
    zarr_out = is_zarr_path(out)
    if resume:
        for p in (work, out):
            if os.path.exists(p) and not _writable(p):
                raise ValueError(f"cannot resume into {p!r}: it is not writable")
        if zarr_out and os.path.isdir(out):
            _check_resumed_output(out, tuple(stack.shape), tile)
    if not np.issubdtype(stack.dtype, np.integer) and not np.issubdtype(stack.dtype,
                                                                          np.floating):
        raise ValueError(f"the stack {os.fspath(stack_path)!r} holds {stack.dtype} data; "
                         "expected intensities (integers or floats)")


def _write_output(u, out, shape, info, voxel, *, n_iter, tile, resume, workers):
    """The iterate written out: into the OME-Zarr output (the last iteration has written
    every chunk of it; a run interrupted before this step, by an earlier version, may have
    left some to write) only the chunks missing, chunks of one plane and one tile's lateral
    size, each in one tile of the iterate, read once for all the chunks it holds, a tile
    at a time on each thread; or as one TIFF. Returns the chunks written by this run
    (the last iteration's included) and their total."""
    from .io import write_tiff
    from .ome_zarr import missing_chunks, open_ome_zarr_output

    written = total = 1
    if is_zarr_path(out):
        arr = open_ome_zarr_output(out)
        todo = missing_chunks(arr, out)
        total = int(np.prod([-(-n // c) for n, c in zip(arr.shape, arr.chunks,
                                                          strict=True)]))
        cy, cx = arr.chunks[1:]
        by_tile: dict[tuple[int, int], list] = {}
        for idx in todo:
            tile_y = int(np.searchsorted(np.cumsum(u.chunks[1]), idx[1] * cy, side="right"))
            tile_x = int(np.searchsorted(np.cumsum(u.chunks[2]), idx[2] * cx, side="right"))
            by_tile.setdefault((tile_y, tile_x), []).append(idx)
        starts_y = np.cumsum((0,) + u.chunks[1])
        starts_x = np.cumsum((0,) + u.chunks[2])

        def write_tile(item) -> None:
            (ty, tx), chunks = item
            y0, y1 = int(starts_y[ty]), int(starts_y[ty + 1])
            x0, x1 = int(starts_x[tx]), int(starts_x[tx + 1])
            part = np.asarray(u[:, y0:y1, x0:x1].compute(scheduler="sync"), np.float32)
            for iz, iy, ix in chunks:
                ys = slice(iy * cy, min((iy + 1) * cy, arr.shape[1]))
                xs = slice(ix * cx, min((ix + 1) * cx, arr.shape[2]))
                arr[iz, ys, xs] = part[iz, ys.start - y0:ys.stop - y0,
                                       xs.start - x0:xs.stop - x0]

        # a tile at a time on each thread (the budget's tiles at once): the iterations
        # are over, their memory free
        map_threads(write_tile, list(by_tile.items()), workers)
        written = len(todo)
    else:
        write_tiff(out, np.asarray(u.compute(), np.float32),
                   pixel_size=info.pixel_size if voxel is None else voxel[2],
                   z_spacing=None if voxel is None else voxel[0], metadata={"deblur3d": {
                       "method": "rl", "iterations": n_iter, "tile": tile}})
    return written, total


deblur_to_store = drained(iter_deblur_to_store, "deblur_to_store")


__all__ = ["VOXEL_RTOL", "StoreRun", "deblur_to_store", "is_zarr_path",
           "iter_deblur_to_store", "stack_voxel_size", "work_folder"]
