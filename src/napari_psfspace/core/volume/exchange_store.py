"""The passes of the exchanging tiles over a work folder: each tile a task that reads its
own window from the folder and writes its own tile back.

With the iterates in a folder (a volume larger than memory), a pass holds nothing but
the tasks running: a tile's task reads the window it needs (the tile and a ring of
``P // 2``) straight from the folder, computes, and writes its tile; no task writes
another's voxels, and none waits for another's. The memory a pass holds is then the
tasks' at once (:func:`~.exchange3d.task_bytes`), whatever the volume's size: a volume
larger than the machine takes longer, not more memory.

Each array of the folder is one float32 file of lateral chunks ``(Z, C, C)``, each
chunk one run of bytes (:class:`RawVolume`), read and written by box through a mapping
of each chunk opened for that access alone: a box costs a copy to or from the page
cache, with no codec and no bookkeeping between the threads (Zarr's took more time than
the copies), and the process holds no more of the file than the chunks it copies (a
mapping's pages count in its resident memory until it is closed). ``C`` divides the
tile, so every chunk lies in one tile and is written by one task. The files are scratch: the
run's ``state.json`` names the last iteration whose iterate is whole (``u`` alternates
between two files), and a resumed run makes the others again.
"""

from __future__ import annotations

import os

import numpy as np

from .deconvolve3d import TINY

#: Lateral chunk of the work folder's files, pixels, where it divides the tile (else the
#: tile): a window of a tile ``T`` reads at most ``(T + 2 ring + 2 C)²`` pixels. A chunk
#: is ``Z x C x C`` float32 in one run of bytes, so a window read from disk (a volume
#: larger than the page cache) reads whole runs, not one short row per page.
STORE_CHUNK = 128


def store_chunk(tile: int, side: int) -> int:
    """The work files' lateral chunk for tiles of ``tile`` px on a field ``side`` px wide:
    :data:`STORE_CHUNK`, halved down to 16 px while it does not divide the tile or is
    over a quarter of it (a window then reads at most half a tile beyond itself); the
    tile itself where no such chunk divides it."""
    c = STORE_CHUNK
    while c > 16 and (tile % c or 4 * c > tile):
        c //= 2
    return c if tile % c == 0 else min(int(tile), int(side))


class RawVolume:
    """A float32 volume ``(Z, H, W)`` in one uncompressed file of lateral chunks: a
    ``.npy`` of shape ``(ceil(H / C), ceil(W / C), Z, C, C)`` (the field padded to whole
    chunks), read and written by box (``vol[region]``, ``vol[region] = values``)
    through a mapping of each chunk the box meets, opened for that access alone: a copy
    to or from the page cache, no codec, and the process holds no more of the file than
    the chunks it copies. Picklable (a path), so a cluster's workers open it where it
    lies; it has ``shape``, ``dtype`` and ``ndim``: ``dask.array.from_array`` reads it.

    Two tasks may write at once where no chunk holds voxels of both (each chunk lies in
    one tile: :func:`store_chunk` divides the tile)."""

    def __init__(self, path: str | os.PathLike, shape, chunk: int, *,
                 create: bool = False) -> None:
        self.path = os.fspath(path)
        self.shape = tuple(int(v) for v in shape)
        self.chunk = c = int(chunk)
        self.dtype, self.ndim = np.dtype(np.float32), 3
        z, h, w = self.shape
        self.grid = (-(-h // c), -(-w // c))
        layout = (*self.grid, z, c, c)
        if create:  # sparse until written
            mm = np.lib.format.open_memmap(self.path, mode="w+", dtype=np.float32,
                                           shape=layout)
            del mm
        with open(self.path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = (np.lib.format.read_array_header_1_0 if version == (1, 0) else
                    np.lib.format.read_array_header_2_0)
            found, fortran, dtype = read(f)
            self.offset = f.tell()
        if fortran or np.dtype(dtype) != np.float32 or tuple(found) != layout:
            raise ValueError(f"{self.path!r} is not a float32 volume {self.shape} in chunks "
                             f"of {c} px: it holds {np.dtype(dtype)} {tuple(found)}")

    def _boxes(self, region):
        """For each chunk the box meets: its index, the box's part in the chunk and in
        an array of the box's shape."""
        if not isinstance(region, tuple):
            region = (region,)
        region = region + (slice(None),) * (3 - len(region))
        box = tuple(range(n)[r] if isinstance(r, slice) else None
                    for r, n in zip(region, self.shape, strict=True))
        if any(b is None or b.step != 1 for b in box):
            raise ValueError(f"a RawVolume is read and written by boxes of slices, got "
                             f"{region!r}")
        zs, ys, xs = box
        c = self.chunk
        parts = []
        for i in range(ys.start // c, -(-ys.stop // c)):
            y0, y1 = max(ys.start, i * c), min(ys.stop, (i + 1) * c)
            for j in range(xs.start // c, -(-xs.stop // c)):
                x0, x1 = max(xs.start, j * c), min(xs.stop, (j + 1) * c)
                parts.append(((i, j),
                              (slice(zs.start, zs.stop), slice(y0 - i * c, y1 - i * c),
                               slice(x0 - j * c, x1 - j * c)),
                              (slice(None), slice(y0 - ys.start, y1 - ys.start),
                               slice(x0 - xs.start, x1 - xs.start))))
        return (len(zs), len(ys), len(xs)), parts

    def _at(self, index) -> int:
        z, c = self.shape[0], self.chunk
        return self.offset + (index[0] * self.grid[1] + index[1]) * z * c * c * 4

    def _map(self, index, mode: str) -> np.memmap:
        z, c = self.shape[0], self.chunk
        return np.memmap(self.path, dtype=np.float32, mode=mode, offset=self._at(index),
                         shape=(z, c, c))

    def _run(self, index, inside) -> int | None:
        """Where a chunk's part starts in the file where it is one run of bytes (whole
        laterally: a slab of planes of the chunk), else None."""
        zs, ys, xs = inside
        c = self.chunk
        if (ys.start, ys.stop, xs.start, xs.stop) != (0, c, 0, c):
            return None
        return self._at(index) + zs.start * c * c * 4

    def __getitem__(self, region) -> np.ndarray:
        shape, parts = self._boxes(region)
        out = np.empty(shape, np.float32)
        with open(self.path, "rb", buffering=0) as f:
            for index, inside, there in parts:
                at = self._run(index, inside)
                if at is not None:  # one read of its run of bytes, no mapping
                    run = np.empty((shape[0], self.chunk, self.chunk), np.float32)
                    f.seek(at)
                    if f.readinto(memoryview(run).cast("B")) != run.nbytes:
                        raise OSError(f"{self.path!r} is shorter than its header says")
                    out[there] = run
                    continue
                mm = self._map(index, "r")
                out[there] = mm[inside]
                del mm  # unmapped: the copy is all this process holds
        return out

    def __setitem__(self, region, values) -> None:
        shape, parts = self._boxes(region)
        values = np.broadcast_to(np.asarray(values, dtype=np.float32), shape)
        fd = os.open(self.path, os.O_WRONLY)
        try:
            for index, inside, there in parts:
                at = self._run(index, inside)
                if at is not None:
                    # the run of bytes written whole: the kernel need not read the old
                    # pages first, as a mapping's write to a page not in memory does
                    run = memoryview(np.ascontiguousarray(values[there])).cast("B")
                    done = 0
                    while done < run.nbytes:  # a write may take part of the bytes
                        done += os.pwrite(fd, run[done:], at + done)
                    continue
                mm = self._map(index, "r+")
                mm[inside] = values[there]  # into the page cache; the kernel writes it back
                del mm
        finally:
            os.close(fd)


def open_array(store, name: str, shape, chunk: int, *, create: bool = False) -> RawVolume:
    """The float32 volume ``name`` of the work folder ``store`` (shape ``(Z, H, W)``, in
    lateral chunks of ``chunk`` px): created (sparse) with ``create``, else the one
    there."""
    return RawVolume(os.path.join(os.fspath(store), name), shape, chunk, create=create)


class TilePass:
    """One pass over the tiles, as a picklable task of one tile ``(iy, ix)`` (a cluster
    runs it where the folder is); ``tasks`` holds the "apply" and "adjoint"
    :class:`~.exchange3d.WindowTask`:

    - "norm": ``H^T 1`` on the tile into ``target``;
    - "ratio": ``y / max(H u + b, tiny)`` on the tile into ``target``, ``u`` the array
      ``source`` read on the tile and a ring;
    - "update": ``max(u H^T r / max(norm, floor), 0)`` on the tile into ``target``, ``r``
      the array ``source`` read on the tile and a ring and ``u`` the array ``factor``;
      and into the Zarr array at the path ``also`` where one is given (the run's
      output, written as the last iteration makes it: no second reading of it).

    An iterate named None is the constant ``start`` (the first iteration's)."""

    def __init__(self, kind: str, tasks: dict, store, edges_y, edges_x, *,
                 target: str, source: str | None = None, factor: str | None = None,
                 start: float = 0.0, background: float = 0.0, floor: float = TINY,
                 also: str | os.PathLike | None = None, chunk: int) -> None:
        self.kind, self.tasks, self.store = kind, dict(tasks), os.fspath(store)
        self.chunk = int(chunk)
        self.edges_y, self.edges_x = list(edges_y), list(edges_x)
        self.target, self.source, self.factor = target, source, factor
        self.start, self.background, self.floor = float(start), float(background), float(floor)
        self.also = None if also is None else os.fspath(also)
        self._arrays: dict = {}

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_arrays": {}}  # a worker opens its own

    def _read(self, name: str | None, region: tuple) -> np.ndarray:
        z = self.tasks["adjoint"].operator.image_shape[0]
        if name is None:  # the constant start, or the ones of H^T 1
            value = 1.0 if self.kind == "norm" else self.start
            return np.full((z, region[1].stop - region[1].start,
                            region[2].stop - region[2].start), value, np.float32)
        return np.asarray(self._open(name)[region], dtype=np.float32)

    def _open(self, name: str):
        arr = self._arrays.get(name)
        if arr is None:
            arr = self._arrays[name] = open_array(
                self.store, name, self.tasks["adjoint"].operator.image_shape, self.chunk)
        return arr

    def _around(self, iy: int, ix: int, rings: int) -> tuple[slice, slice, slice]:
        """The tile and ``rings`` rings around it, clipped to the field."""
        (ty0, ty1), (tx0, tx1) = self.edges_y[iy], self.edges_x[ix]
        _, h, w = self.tasks["adjoint"].operator.image_shape
        d = rings * self.tasks["adjoint"].ring
        return (slice(None), slice(max(ty0 - d, 0), min(ty1 + d, h)),
                slice(max(tx0 - d, 0), min(tx1 + d, w)))

    @staticmethod
    def _within(inner: tuple, outer: tuple) -> tuple[slice, slice, slice]:
        """``inner``'s place in an array that holds ``outer``."""
        return (slice(None),) + tuple(slice(i.start - o.start, i.stop - o.start)
                                      for i, o in zip(inner[1:], outer[1:], strict=True))

    def _adjoint_on_tile(self, v: np.ndarray, where: tuple, tile: tuple) -> np.ndarray:
        """``H^T`` of ``v`` (held on ``where``) on ``tile``."""
        inner = self._within(tile, where)
        box = (inner[1].start, inner[1].stop, inner[2].start, inner[2].stop)
        return self.tasks["adjoint"].product(v, where[1].start, where[2].start,
                                             tile=box)[inner]

    def __call__(self, iy: int, ix: int) -> None:
        from ..common.heap import keep_heap_in_worker

        keep_heap_in_worker()  # a cluster's worker process: its heap kept for its tasks
        tile, where = self._around(iy, ix, 0), self._around(iy, ix, 1)
        window = self._read(self.source, where)
        if self.kind == "ratio":
            out = self.tasks["apply"].product(window, where[1].start, where[2].start)
            out = out[self._within(tile, where)]
            out += np.float32(self.background)
            np.maximum(out, np.float32(TINY), out=out)
            np.divide(self._read("data", tile), out, out=out)
        else:
            out = self._adjoint_on_tile(window, where, tile)
        del window
        if self.kind == "update":
            out *= self._read(self.factor, tile)
            out /= np.maximum(self._read("norm", tile), np.float32(self.floor))
            np.maximum(out, np.float32(0), out=out)
        out = np.ascontiguousarray(out, dtype=np.float32)
        self._open(self.target)[tile] = out
        if self.also is not None:
            also = self._arrays.get(self.also)
            if also is None:
                import zarr

                also = self._arrays[self.also] = zarr.open_array(
                    self.also, mode="r+").with_config({"write_empty_chunks": True})
            also[tile] = out


def _read_boxes(stack, edges_y, edges_x) -> list[tuple]:
    """The boxes ``(zs, ys, xs)`` the stack is read by: for a dask array whose chunks
    are no larger than a tile's volume, its own chunks laterally and slabs of whole
    chunks in z up to a tile's volume (each compressed chunk read once, where a tile
    narrower than a chunk would read it once a tile); else the tiles, whole in z."""
    z = stack.shape[0]
    tiles = [((0, z), ys, xs) for ys in edges_y for xs in edges_x]
    chunks = getattr(stack, "chunks", None)
    if chunks is None or not isinstance(chunks[0], tuple):
        return tiles
    tile_volume = z * max(b - a for a, b in edges_y) * max(b - a for a, b in edges_x)

    def edges(sizes):
        ends = np.cumsum((0,) + tuple(sizes))
        return list(zip(ends[:-1].tolist(), ends[1:].tolist(), strict=True))

    lateral = max(chunks[1]) * max(chunks[2])
    if max(chunks[0]) * lateral > tile_volume:
        return tiles
    slabs, z0, n = [], 0, 0
    for a, b in edges(chunks[0]):  # whole z chunks, up to a tile's volume a slab
        if n and (n + b - a) * lateral > tile_volume:
            slabs.append((z0, a))
            z0, n = a, 0
        n += b - a
    slabs.append((z0, z))
    return [(zs, ys, xs) for ys in edges(chunks[1]) for xs in edges(chunks[2])
            for zs in slabs]


def write_data(stack, store, edges_y, edges_x, *, chunk: int, workers: int) -> None:
    """The stack in float32, clipped at 0, into the store's ``data``, a box at a time
    (:func:`_read_boxes`; ``stack`` a dask array read lazily, or an ndarray)."""
    import dask

    arr = open_array(store, "data", stack.shape, chunk)

    def one(zs, ys, xs) -> None:
        box = (slice(*zs), slice(*ys), slice(*xs))
        part = stack[box]
        if hasattr(part, "compute"):
            part = part.compute(scheduler="sync")
        part = np.asarray(part, dtype=np.float32)
        arr[box] = np.clip(part, 0, None, out=part)

    jobs = [dask.delayed(one)(*b) for b in _read_boxes(stack, edges_y, edges_x)]
    dask.compute(*jobs, scheduler="threads", num_workers=workers)


def run_pass(task: TilePass, n_y: int, n_x: int, config: dict) -> None:
    """Every tile's task of a pass, as dask tasks (threads, or the cluster's), the
    largest tiles first (the field's last row and column may be narrower: started last,
    they fill the gaps the others leave)."""
    import dask

    def area(t):
        (y0, y1), (x0, x1) = task.edges_y[t[0]], task.edges_x[t[1]]
        return -(y1 - y0) * (x1 - x0)

    order = sorted(((iy, ix) for iy in range(n_y) for ix in range(n_x)), key=area)
    jobs = [dask.delayed(task, pure=False)(iy, ix) for iy, ix in order]
    dask.compute(*jobs, **config)


__all__ = ["RawVolume", "STORE_CHUNK", "TilePass", "open_array", "run_pass", "store_chunk",
           "write_data"]
