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

from .core.common.progress import Progress, run_with_progress
from .core.volume.blocks3d import BLOCK, RTOL
from .core.volume.exchange3d import iter_richardson_lucy_3d_exchange, plan_for_memory
from .core.volume.operator3d import ProductConvolution3D


@dataclass
class StoreRun:
    """What :func:`deblur_to_store` did: the tile size, the iterations, the output's
    chunks written by this run (a resumed run writes only the missing ones)."""

    tile: int
    iterations: int
    chunks_written: int
    chunks_total: int
    background: float | None


def is_zarr_path(path: str | os.PathLike) -> bool:
    """Whether an output path names an OME-Zarr folder (``.zarr``)."""
    return os.fspath(path).rstrip("/\\").lower().endswith(".zarr")


def work_folder(output: str | os.PathLike) -> str:
    """The folder of a run's iterates, beside its output."""
    return os.fspath(output).rstrip("/\\") + ".iterates"


def iter_deblur_to_store(stack_path: str | os.PathLike, operator: ProductConvolution3D,
                         output: str | os.PathLike, *, n_iter: int = 50,
                         memory: float | None = None, tile: int | None = None,
                         background: float | None = None, rtol: float = RTOL,
                         block: int = BLOCK, resume: bool = False, client=None,
                         workers: int | None = None):
    """Generator form of :func:`deblur_to_store` (progress records; the
    :class:`StoreRun` as its value)."""
    from .io import read_stack, write_tiff
    from .ome_zarr import create_ome_zarr, missing_chunks, open_ome_zarr_output

    out = os.fspath(output)
    work = work_folder(out)
    parent = os.path.dirname(os.path.abspath(out.rstrip("/\\")))
    if not os.path.isdir(parent):
        raise ValueError(f"cannot write {out}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
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
    stack, info = read_stack(stack_path, lazy=True)
    if tuple(stack.shape[1:]) != tuple(operator.shape[1:]):
        raise ValueError(f"the stack has slices of {tuple(stack.shape[1:])}, the model acts "
                         f"on {tuple(operator.shape[1:])}")
    depth = int(stack.shape[0])
    if tile is None and memory is not None:
        tile, workers = plan_for_memory(operator, depth, memory, block=block,
                                        workers=workers)
    tile = 4 * block if tile is None else tile
    os.makedirs(work, exist_ok=True)
    u = yield from iter_richardson_lucy_3d_exchange(
        stack, operator, n_iter=n_iter, background=background, tile=tile, block=block,
        rtol=rtol, store=work, resume=resume, client=client, workers=workers)
    yield Progress("write", 1.0, f"writing {out}")
    voxel = None
    if info.pixel_size is not None:
        voxel = (info.z_spacing or 1.0, info.pixel_size, info.pixel_size)
    written = total = 1
    if zarr_out:
        # chunks of one plane and one tile's lateral size: each lies in one tile of the
        # iterate, which is read once for all the chunks it holds
        arr = (open_ome_zarr_output(out) if resume and os.path.isdir(out) else
               create_ome_zarr(out, tuple(stack.shape), voxel_size=voxel, chunk=tile))
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
        for (ty, tx), chunks in by_tile.items():
            y0, y1 = int(starts_y[ty]), int(starts_y[ty + 1])
            x0, x1 = int(starts_x[tx]), int(starts_x[tx + 1])
            part = np.asarray(u[:, y0:y1, x0:x1].compute(), np.float32)
            for iz, iy, ix in chunks:
                ys = slice(iy * cy, min((iy + 1) * cy, arr.shape[1]))
                xs = slice(ix * cx, min((ix + 1) * cx, arr.shape[2]))
                arr[iz, ys, xs] = part[iz, ys.start - y0:ys.stop - y0,
                                       xs.start - x0:xs.stop - x0]
        written = len(todo)
    else:
        write_tiff(out, np.asarray(u.compute(), np.float32),
                   pixel_size=info.pixel_size, metadata={"deblur3d": {
                       "method": "rl", "iterations": n_iter, "tile": tile}})
    shutil.rmtree(work, ignore_errors=True)
    return StoreRun(tile, n_iter, written, total, background)


def deblur_to_store(stack_path, operator: ProductConvolution3D, output, *,
                    n_iter: int = 50, memory: float | None = None, tile: int | None = None,
                    background: float | None = None, rtol: float = RTOL,
                    block: int = BLOCK, resume: bool = False, client=None,
                    workers: int | None = None, progress=None) -> StoreRun:
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
    progress : callable, optional
        Called with each progress record.

    Returns
    -------
    StoreRun
    """
    return run_with_progress(iter_deblur_to_store(
        stack_path, operator, output, n_iter=n_iter, memory=memory, tile=tile,
        background=background, rtol=rtol, block=block, resume=resume, client=client,
        workers=workers), progress)


__all__ = ["StoreRun", "deblur_to_store", "is_zarr_path", "iter_deblur_to_store",
           "work_folder"]
