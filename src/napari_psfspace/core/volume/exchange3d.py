"""3D Richardson-Lucy on lateral tiles that exchange their margins at every iteration:
the whole volume's iterates, a tile at a time.

The blocked operator (:mod:`.blocks3d`) cuts the field into ``B x B`` blocks, each with
its own kernels (compressed from the block's own maps, so they depend on nothing else).
``H u`` at a pixel is the light of the pixels within ``P // 2`` of it, each through its
own block's kernels; ``H^T v`` likewise reads ``v`` within ``P // 2``. So a tile gets
exact values of both from a window of the tile and a ring of ``P // 2`` pixels, when the
window's blocks are the field's blocks cut by the window, each with its whole block's
kernels (``BlockedOperator3D(window=...)``). One iteration is::

    r = y / max(H u + b, tiny)
    u = max(u * H^T r / max(H^T 1, tiny max(H^T 1)), 0)

It is two passes over the tiles, each tile's window overlapping its neighbours by the
ring, with ``u`` and ``r`` held between them in memory (``persist``: the threads' or a
``dask.distributed`` cluster's; ``dask.array.map_overlap`` assembles each window from
the neighbouring chunks) or in a work folder (``store``: the volume larger than memory;
each tile a task reading its window from the folder's files, :mod:`.exchange_store`).
The adjoint's tile needs only the blocks that meet it (each block's ``H^T r`` reads
``r`` on the block and the ring); the apply's needs the ring's blocks too, their light
reaching into the tile. Every voxel
then follows the same arithmetic as
:func:`~napari_psfspace.core.volume.deconvolve3d.richardson_lucy_3d` on the whole volume
with the same blocks, up to the order of float32 additions: the tiles leave no seam.
Independent tiles with a fixed margin (:mod:`.tiles3d`) cannot: a bead's influence
spreads by ``P // 2`` pixels every iteration.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Generator

import numpy as np
import scipy.fft

from ..common.atomic import atomic_write
from ..common.device import ArrayModule, array_module
from ..common.progress import Progress
from ..common.twins import drained
from ..common.validate import check_background, check_int, check_positive
from .blocks3d import BLOCK, RTOL, BlockedOperator3D
from .deconvolve3d import TINY, check_stack, stack_statistics
from .operator3d import ProductConvolution3D
from .tiles3d import tile_sizes

#: Default lateral tile size, pixels (a multiple of the default block: no tile cuts a
#: block but at the field's edge).
TILE = 4 * BLOCK
#: Window volumes a device must hold free for a window to go there whole (the window, the
#: product and a block's FFT buffers beside them); else its blocks are copied one by one.
DEVICE_VOLUMES = 4


def ring_width(operator: ProductConvolution3D) -> int:
    """The margin each tile's window reads, pixels: the kernel's half-width ``P // 2``."""
    return int(operator.kernel_shape[1] // 2)


def task_bytes(operator: ProductConvolution3D, depth: int, tile: int, block: int) -> int:
    """Memory one tile's pass holds at its peak, bytes (a bound: ``bench/run.py
    deblur3d_scale`` measures the whole run's peak against it): its window ``(tile + 2
    ring)`` wide, six volumes of it in float32 (the window read or assembled from the neighbouring
    chunks, the product, its trimmed copy, and the tile's data, iterate and norm in the
    elementwise step), the window's maps in float64 and
    float32, and spectra of a whole block's FFT shape: the basis's ``I`` twice over (the
    whole blocks' and those cut by the window's edge), a block's kernels (at most ``I``)
    and two buffers."""
    n, p, _ = operator.kernel_shape
    side = tile + 2 * ring_width(operator)
    fz = scipy.fft.next_fast_len(depth + n // 2, real=True)
    fl = scipy.fft.next_fast_len(block + p - 1, real=True)
    spectrum = fz * fl * (fl // 2 + 1) * 8
    i = operator.n_psf
    return int(6 * depth * side * side * 4 + i * side * side * 12
               + (3 * i + 2) * spectrum)


#: Memory of the interpreter, NumPy, SciPy and dask before any volume, bytes: the part of
#: a budget no tile can use.
BASE_BYTES = 400 * 2**20


def plan_for_memory(operator: ProductConvolution3D, depth: int, memory: float, *,
                    block: int = BLOCK, workers: int | None = None) -> tuple[int, int]:
    """The tile size and the tiles at once for a memory budget of ``memory`` bytes.

    The largest multiple of ``block`` whose passes, ``workers`` at once, fit beside
    :data:`BASE_BYTES` (:func:`task_bytes`); where even one block's tile does not fit,
    fewer at once (down to one). Then evened out: the axes cut into as few tiles as that
    size needs, of equal sizes, and at least as many tiles as run at once where the
    field allows.

    Returns
    -------
    tile : int
        Lateral tile size, pixels.
    workers : int
        Tiles computed at once.

    Raises
    ------
    ValueError
        Where one tile of one block does not fit: the line names ``memory`` and the
        least that would do.
    """
    from ..common.threads import default_workers

    workers = default_workers() if workers is None else max(1, int(workers))
    _, h, w = operator.image_shape

    least = min(block, max(h, w))

    def fits(tile: int, n: int) -> bool:
        return BASE_BYTES + n * task_bytes(operator, depth, tile, block) <= memory

    while workers > 1 and not fits(least, workers):
        workers -= 1
    if not fits(least, workers):
        need = BASE_BYTES + task_bytes(operator, depth, least, block)
        raise ValueError(f"`memory` must be at least {need / 2**30:.2f} GiB for one tile "
                         f"of {least} px on {depth} planes, got {memory / 2**30:.2f} GiB")
    most = -(-max(h, w) // block) * block
    tile = block
    while tile + block <= most and fits(tile + block, workers):
        tile += block
    while tile > block and -(-h // tile) * -(-w // tile) < workers:
        tile -= block  # every thread a tile
    # as few tiles as that size needs along each axis, of near sizes (no thread is left
    # with a sliver while the others wait), in whole blocks (a block cut by a tile's edge
    # would take two smaller FFTs)
    even = max(-(-n // -(-n // tile)) for n in (h, w))
    return min(tile, -(-even // block) * block), workers


def write_state(store, state: dict) -> None:
    """``state.json`` in ``store``, replaced atomically: the iterations done and the
    settings they were done with."""
    atomic_write(os.path.join(os.fspath(store), "state.json"),
                 lambda f: json.dump(state, f), mode="w", encoding="utf-8")


def read_state(store, settings: dict) -> dict | None:
    """The state of an interrupted run in ``store`` (None where it finished no
    iteration); one line naming what differs when its settings are not ``settings``."""
    path = os.path.join(os.fspath(store), "state.json")
    if not os.path.exists(path):
        return None
    try:
        with open(path, encoding="utf-8") as f:
            state = json.load(f)
        done = int(state["done"])
        float(state["background"]), float(state["start"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"nothing to resume in {os.fspath(store)!r}: no readable "
                         f"state.json ({type(exc).__name__})") from None
    for key, want in settings.items():
        if state.get(key) != want:
            raise ValueError(f"cannot resume: the interrupted run had {key} "
                             f"{state.get(key)!r}, this one {want!r}")
    if done < 0:
        raise ValueError(f"cannot resume: state.json says {done} iterations done")
    return state


class WindowTask:
    """The blocked operator's product (``kind`` "apply" or "adjoint") on one tile's
    window, as ``map_overlap`` calls it; picklable, so a cluster can run it. The
    window's origin is its chunk's start less the ring (clipped at 0)."""

    def __init__(self, operator: ProductConvolution3D, kind: str, starts_y, starts_x,
                 ring: int, block: int, rtol: float,
                 device: str | ArrayModule = "cpu") -> None:
        self.operator, self.kind, self.ring = operator, kind, int(ring)
        self.starts_y, self.starts_x = tuple(starts_y), tuple(starts_x)
        self.block, self.rtol = int(block), float(rtol)
        # a name is resolved where the task runs: each worker process its own device
        self.device = device
        self._am: ArrayModule | None = None
        # for every window: the basis spectra by FFT shape, each field block's kernels
        self.spectra: dict = {}
        self.kernels: dict = {}

    def __getstate__(self) -> dict:
        # a worker forms its own caches and finds its own device
        return {**self.__dict__, "spectra": {}, "kernels": {}, "_am": None}

    def module(self) -> ArrayModule:
        """The array module the windows' blocks run on, found once a process."""
        if self._am is None:
            self._am = array_module(self.device)
        return self._am

    def __call__(self, window: np.ndarray, block_info=None) -> np.ndarray:
        _, iy, ix = block_info[0]["chunk-location"]
        _, h, w = self.operator.image_shape
        ty0, tx0 = self.starts_y[iy], self.starts_x[ix]
        ty1 = self.starts_y[iy + 1] if iy + 1 < len(self.starts_y) else h
        tx1 = self.starts_x[ix + 1] if ix + 1 < len(self.starts_x) else w
        y0, x0 = max(ty0 - self.ring, 0), max(tx0 - self.ring, 0)
        return self.product(window, y0, x0, tile=(ty0 - y0, ty1 - y0, tx0 - x0, tx1 - x0))

    def product(self, window: np.ndarray, y0: int, x0: int,
                tile: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """The product on ``window`` (Z, h, w) whose top-left pixel is ``(y0, x0)`` of the
        field; float32 on the host, the window's shape. Where ``tile`` (rows and columns
        of the window) is given, only its values are used: the adjoint then computes the
        blocks that meet it alone (the apply needs every block, the ring's light reaching
        into the tile)."""
        am = self.module()
        # each block is used once a pass: no spectra kept beyond it
        blocked = BlockedOperator3D(self.operator, block=self.block, rtol=self.rtol,
                                    cache_bytes=0, window=(y0, y0 + window.shape[1], x0,
                                                           x0 + window.shape[2]),
                                    basis_spectra=self.spectra,
                                    block_kernels=self.kernels, device=am)
        data = np.ascontiguousarray(window, dtype=np.float32)
        if am.gpu and am.free_bytes() > DEVICE_VOLUMES * data.nbytes:
            data = am.asarray(data)  # the window on the device, its blocks read there
        out = (blocked.apply(data, workers=1) if self.kind == "apply" else
               blocked.adjoint(data, workers=1, region=tile))
        return out if isinstance(out, np.ndarray) else am.to_host(out)


def iter_richardson_lucy_3d_exchange(
    stack,
    operator: ProductConvolution3D,
    *,
    n_iter: int = 50,
    background: float | None = None,
    start: float | None = None,
    tile: int = TILE,
    block: int = BLOCK,
    rtol: float = RTOL,
    store: str | os.PathLike | None = None,
    resume: bool = False,
    client=None,
    workers: int | None = None,
    device: str | ArrayModule = "cpu",
    output: str | os.PathLike | None = None,
) -> Generator[Progress, None, object]:
    """Space-varying Richardson-Lucy on lateral tiles that exchange their margins at
    every iteration (the module's notes): the whole volume's result, tile by tile.

    Parameters
    ----------
    stack : array_like or dask.array.Array of shape (Z, H, W)
        The blurred volume, image units.
    operator : ProductConvolution3D
    n_iter : int
        Iterations.
    background : float, optional
        Constant background, image units; default the stack's
        (:func:`~napari_psfspace.core.volume.deconvolve3d.stack_statistics`).
    start : float, optional
        Starting value; default the stack's mean less the background.
    tile : int
        Lateral tile size, pixels (at least the kernel's; a multiple of ``block``
        cuts no block but at the field's edge).
    block, rtol
        The blocked operator's block size and kernel tolerance
        (:class:`~napari_psfspace.core.volume.blocks3d.BlockedOperator3D`).
    store : str or os.PathLike, optional
        A folder where the iterates are written between the passes (float32 files of
        lateral chunks, :class:`~.exchange_store.RawVolume`: ``data``, the stack clipped at 0,
        ``norm``, ``ratio``, ``u0``, ``u1``, and ``state.json``, the iterations done,
        written after each: ``u`` alternates between two files so that the last finished
        iterate is whole while the next is written; the ratio is made again from it on a
        resume, so one file holds it);
        the result is then the last iterate there, a lazy dask array.
    resume : bool
        Continue from the store's last finished iteration (its settings must be these;
        from the start where it finished none).
    client : dask.distributed.Client, optional
        Runs the tiles on this cluster, the iterates held in its memory.
    workers : int, optional
        Tiles at once on the local threads; default dask's (the cores).
    device : {"cpu", "gpu", "auto"} or ArrayModule
        Where each tile's blocks run (:mod:`~napari_psfspace.core.common.device`). On a
        GPU the local threads run one tile at a time; on a cluster each worker process
        finds its own device (one a worker: ``dask-cuda``'s ``LocalCUDACluster``).
    output : str or os.PathLike, optional
        With ``store``: the path of a Zarr array of the stack's shape, every chunk in
        one tile, that the last iteration writes each tile into as it makes it (a
        result written without reading it back). A resumed run that redoes the last
        iteration writes it again.

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    ndarray or dask.array.Array of shape (Z, H, W), float32
        Equal to :func:`~napari_psfspace.core.volume.deconvolve3d.richardson_lucy_3d`
        with the same ``block``, ``rtol``, background and start, to float32 rounding.
    """

    check_stack(stack, operator)
    n_iter = check_int(n_iter, "n_iter", minimum=1)
    block = check_int(block, "block", minimum=operator.kernel_shape[1])
    tile = check_int(tile, "tile", minimum=operator.kernel_shape[1])
    if not (np.isfinite(rtol) and rtol >= 0):
        raise ValueError(f"`rtol` must be a finite number >= 0, got {rtol!r}")
    if resume and store is None:
        raise ValueError("`resume` needs the `store` of the interrupted run")
    if output is not None and store is None:
        raise ValueError("`output` needs a `store` (the tiles write it from there)")
    am = array_module(device)  # "gpu" without CuPy or a device: one line, no work done
    z, h, w = stack.shape
    settings = {"shape": [z, h, w], "tile": tile, "block": block, "rtol": float(rtol),
                "arrays": "npy chunks"}
    done, u0, b = yield from _starting_point(stack, background, start, store, resume, settings)
    rows, cols, tasks, config = _tasks(operator, (h, w), tile, block, rtol, client, workers,
                                       device, am)
    from ..common.heap import kept_heap
    from ..common.threads import blas_limit

    # tiles on the local threads: no BLAS threads beside them, and the heap kept between
    # their temporaries (a cluster's workers keep their own: TilePass)
    with blas_limit() if client is None else contextlib.nullcontext(), \
            kept_heap() if client is None else contextlib.nullcontext():
        return (yield from _iterate(stack, tasks, store, rows, cols, settings, config,
                                    client, done=done, n_iter=n_iter, background=b,
                                    start=u0, output=output))


def _starting_point(stack, background, start, store, resume, settings):
    """The iterations done, the background and the start: a resumed run's, the ones given,
    or the stack's statistics.
    """
    state = read_state(store, settings) if resume else None
    done = 0
    if state is not None:
        done, b, u0 = state["done"], state["background"], state["start"]
    elif background is not None and start is not None:  # both given: no stack read
        b, u0 = check_background(background, np.inf), check_positive(start, "start")
    else:
        b, mean = stack_statistics(stack, background)  # its refusals before any progress
        yield Progress("setup", 0.0, f"background {b:.4g}, mean {mean:.4g}")
        u0 = max(mean - b, TINY) if start is None else float(start)
    return done, u0, b


def _tasks(operator, shape, tile, block, rtol, client, workers, device, am):
    """The tiles' rows and columns, the apply and adjoint tasks over them and dask's
    configuration."""
    h, w = shape
    ring = ring_width(operator)
    rows, cols = tile_sizes(h, tile, ring), tile_sizes(w, tile, ring)
    starts_y = np.cumsum((0,) + rows)[:-1]
    starts_x = np.cumsum((0,) + cols)[:-1]

    # a device named travels to the workers by name (each finds its own); an array
    # module given as it is runs on the local threads
    where = device if isinstance(device, ArrayModule) else am.name
    tasks = {kind: WindowTask(operator, kind, starts_y, starts_x, ring, block, rtol, where)
             for kind in ("apply", "adjoint")}
    tasks["adjoint"].spectra = tasks["apply"].spectra  # one cache of each for both
    tasks["adjoint"].kernels = tasks["apply"].kernels

    from ..common.threads import dask_workers

    config = ({"scheduler": client.get} if client is not None else
              {"scheduler": "threads",
               "num_workers": 1 if am.gpu else  # one device: its tiles one at a time
               dask_workers() if workers is None else int(workers)})
    return rows, cols, tasks, config


def _iterate(stack, tasks, store, rows, cols, settings, config, client, *, done, n_iter,
             background, start, output=None):
    """The iterations, in the store or in memory (the passes' dask tasks)."""
    import dask
    import dask.array as da

    z, h, w = settings["shape"]
    ring = tasks["apply"].ring
    b, u0 = background, start
    if store is not None:
        return (yield from _iterate_in_store(
            stack, tasks, store, rows, cols, settings, config, done=done, n_iter=n_iter,
            background=b, start=u0, output=output))

    def product(arr, kind):
        return arr.map_overlap(tasks[kind], depth={0: 0, 1: ring, 2: ring}, boundary="none",
                               dtype=np.float32, trim=True, allow_rechunk=False,
                               meta=np.empty((0, 0, 0), np.float32))

    def hold(arr):
        """The array computed once and held in memory (the threads' or the cluster's)."""
        return client.persist(arr) if client is not None else arr.persist()

    chunks = ((z,), rows, cols)
    lazy = isinstance(stack, da.Array)
    y = stack.rechunk(chunks) if lazy else da.from_array(np.asarray(stack), chunks=chunks)
    y = da.clip(y.astype(np.float32), 0, None)
    with dask.config.set(config):
        if client is not None:  # the stack sent to the cluster once, not in every graph
            y = hold(y)
        yield Progress("setup", 0.0, "H^T 1")
        norm = hold(product(da.ones((z, h, w), np.float32, chunks=chunks), "adjoint"))
        u = da.full((z, h, w), np.float32(u0), dtype=np.float32, chunks=chunks)
        top = float(norm.max().compute())
        norm = da.maximum(norm, np.float32(TINY * max(top, 1.0)))
        for k in range(n_iter):
            forward = product(u, "apply")
            ratio = hold(y / da.maximum(forward + np.float32(b), np.float32(TINY)))
            yield Progress("iteration", (k + 0.5) / n_iter,
                           f"iteration {k + 1} of {n_iter}: H u on every tile")
            u = hold(da.maximum(u * product(ratio, "adjoint") / norm, np.float32(0)))
            yield Progress("iteration", (k + 1) / n_iter, f"iteration {k + 1} of {n_iter}")
        return np.asarray(u.compute())


def _iterate_in_store(stack, tasks, store, rows, cols, settings, config, *, done, n_iter,
                      background, start, output=None):
    """The iterations with the arrays in the store, a task a tile reading its window
    from it (:mod:`.exchange_store`); returns the last iterate, a lazy dask array."""
    import dask.array as da

    from .exchange_store import TilePass, open_array, run_pass, store_chunk, write_data

    z, h, w = settings["shape"]
    edges_y = [(int(a), int(a + n)) for a, n in zip(np.cumsum((0,) + rows)[:-1], rows,
                                                    strict=True)]
    edges_x = [(int(a), int(a + n)) for a, n in zip(np.cumsum((0,) + cols)[:-1], cols,
                                                    strict=True)]
    grid = (len(rows), len(cols))
    folder = os.fspath(store)

    chunk = store_chunk(settings["tile"], max(h, w))

    def one_pass(kind, target, **kw):
        run_pass(TilePass(kind, tasks, folder, edges_y, edges_x, target=target, chunk=chunk,
                          **kw), *grid, config)

    if not done:
        for name in ("data", "norm", "ratio", "u0", "u1"):
            open_array(folder, name, (z, h, w), chunk, create=True)
        yield Progress("setup", 0.0, "the stack into the store, a chunk at a time")
        write_data(stack, folder, edges_y, edges_x, chunk=chunk,
                   workers=config.get("num_workers") or 1)
        yield Progress("setup", 0.0, "H^T 1")
        one_pass("norm", "norm")
    chunks = ((z,), tuple(rows), tuple(cols))
    top = float(da.from_array(open_array(folder, "norm", (z, h, w), chunk), chunks=chunks,
                              asarray=False)
                .max().compute(**config))
    floor = TINY * max(top, 1.0)
    for k in range(done, n_iter):
        previous = None if k == 0 else f"u{(k - 1) % 2}"
        one_pass("ratio", "ratio", source=previous, start=start, background=background)
        yield Progress("iteration", (k + 0.5) / n_iter,
                       f"iteration {k + 1} of {n_iter}: H u on every tile")
        one_pass("update", f"u{k % 2}", source="ratio", factor=previous, start=start,
                 floor=floor, also=output if k == n_iter - 1 else None)
        write_state(store, {**settings, "done": k + 1, "background": background,
                            "start": start})
        yield Progress("iteration", (k + 1) / n_iter, f"iteration {k + 1} of {n_iter}")
    return da.from_array(open_array(folder, f"u{(n_iter - 1) % 2}", (z, h, w), chunk),
                         chunks=chunks, asarray=False)


richardson_lucy_3d_exchange = drained(iter_richardson_lucy_3d_exchange,
                                      "richardson_lucy_3d_exchange")


__all__ = ["BASE_BYTES", "DEVICE_VOLUMES", "TILE", "WindowTask", "iter_richardson_lucy_3d_exchange",
           "read_state", "richardson_lucy_3d_exchange", "ring_width", "task_bytes",
           "plan_for_memory", "write_state"]
