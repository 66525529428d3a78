"""The passes of the exchanging tiles over a Zarr store: each tile a task that reads its
own window from the store and writes its own tile back.

With the iterates in a store (a volume larger than memory), a pass holds nothing but
the tasks running: a tile's task reads the window it needs (the tile and a ring of
``P // 2``) straight from the store, computes, and writes the tile's chunks; no task
shares a chunk with another, and none waits for another's. The memory a pass holds is
then the tasks' at once (:func:`~.exchange3d.task_bytes`), whatever the volume's size:
a volume larger than the machine takes longer, not more memory.

The store's arrays are chunked ``(Z, C, C)`` with ``C`` = :data:`STORE_CHUNK` dividing the
tile, so that a window reads little beyond itself (a ring of ``P // 2`` from the
neighbouring tiles' chunks), and every chunk lies in one tile (each written by one task,
whole: Zarr writes it to a temporary file renamed into place).
"""

from __future__ import annotations

import os

import numpy as np

from .deconvolve3d import TINY

#: Lateral chunk of the store's arrays, pixels, where it divides the tile (else the
#: tile): a window of a tile ``T`` reads at most ``(T + 2 ring + 2 C)²`` pixels. Smaller
#: chunks read less beyond the window but cost Zarr more calls a chunk; this size took
#: the least time a pass on 64-plane stacks (``bench/run.py deblur3d_scale``).
STORE_CHUNK = 128


def store_chunk(tile: int, side: int) -> int:
    """The store's lateral chunk for tiles of ``tile`` px on a field ``side`` px wide:
    :data:`STORE_CHUNK`, halved down to 16 px while it does not divide the tile or is
    over a quarter of it (a window then reads at most half a tile beyond itself); the
    tile itself where no such chunk divides it."""
    c = STORE_CHUNK
    while c > 16 and (tile % c or 4 * c > tile):
        c //= 2
    return c if tile % c == 0 else min(int(tile), int(side))


def open_array(store, name: str, shape, chunk: int, *, create: bool):
    """The float32 array ``name`` in ``store`` (Zarr v2, uncompressed: an iterate's
    float32 noise does not compress, and it is read once a pass), chunked
    ``(Z, chunk, chunk)``, every chunk written even where it is all zeros."""
    import zarr

    path = os.path.join(os.fspath(store), name)
    if create:
        return zarr.create_array(path, shape=tuple(shape), dtype="float32",
                                 chunks=(shape[0], min(chunk, shape[1]),
                                         min(chunk, shape[2])),
                                 fill_value=0, compressors=None, zarr_format=2,
                                 overwrite=True, config={"write_empty_chunks": True})
    return zarr.open_array(path, mode="r+").with_config({"write_empty_chunks": True})


class TilePass:
    """One pass over the tiles, as a picklable task of one tile ``(iy, ix)`` (a cluster
    runs it where the store is):

    - "norm": ``H^T 1`` into ``target``;
    - "ratio": ``y / max(H u + b, tiny)`` into ``target``, ``u`` the array ``source``;
    - "update": ``max(u H^T r / max(norm, floor), 0)`` into ``target``, ``r`` the array
      ``source`` and ``u`` the array ``factor``.

    An iterate named None is the constant ``start`` (the first iteration's)."""

    def __init__(self, kind: str, window_task, store, edges_y, edges_x, *,
                 target: str, source: str | None = None, factor: str | None = None,
                 start: float = 0.0, background: float = 0.0, floor: float = TINY) -> None:
        self.kind, self.task, self.store = kind, window_task, os.fspath(store)
        self.edges_y, self.edges_x = list(edges_y), list(edges_x)
        self.target, self.source, self.factor = target, source, factor
        self.start, self.background, self.floor = float(start), float(background), float(floor)
        self._arrays: dict = {}

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_arrays": {}}  # a worker opens its own

    def _read(self, name: str | None, region: tuple) -> np.ndarray:
        z = self.task.operator.image_shape[0]
        if name is None:  # the constant start, or the ones of H^T 1
            value = 1.0 if self.kind == "norm" else self.start
            return np.full((z, region[1].stop - region[1].start,
                            region[2].stop - region[2].start), value, np.float32)
        return np.asarray(self._open(name)[region], dtype=np.float32)

    def _open(self, name: str):
        arr = self._arrays.get(name)
        if arr is None:
            arr = self._arrays[name] = open_array(self.store, name, None, 0, create=False)
        return arr

    def __call__(self, iy: int, ix: int) -> None:
        (ty0, ty1), (tx0, tx1) = self.edges_y[iy], self.edges_x[ix]
        _, h, w = self.task.operator.image_shape
        ring = self.task.ring
        wy0, wy1 = max(ty0 - ring, 0), min(ty1 + ring, h)
        wx0, wx1 = max(tx0 - ring, 0), min(tx1 + ring, w)
        tile = (slice(None), slice(ty0, ty1), slice(tx0, tx1))
        inner = (slice(None), slice(ty0 - wy0, ty1 - wy0), slice(tx0 - wx0, tx1 - wx0))
        window = self._read(self.source, (slice(None), slice(wy0, wy1), slice(wx0, wx1)))
        out = self.task.product(window, wy0, wx0)[inner]
        del window
        if self.kind == "ratio":
            out += np.float32(self.background)
            np.maximum(out, np.float32(TINY), out=out)
            np.divide(self._read("data", tile), out, out=out)
        elif self.kind == "update":
            out *= self._read(self.factor, tile)
            out /= np.maximum(self._read("norm", tile), np.float32(self.floor))
            np.maximum(out, np.float32(0), out=out)
        self._open(self.target)[tile] = np.ascontiguousarray(out, dtype=np.float32)


def write_data(stack, store, edges_y, edges_x, *, workers: int) -> None:
    """The stack in float32, clipped at 0, into the store's ``data``, a tile at a time
    (each tile read from ``stack``, a dask array read lazily or an ndarray)."""
    import dask

    arr = open_array(store, "data", None, 0, create=False)

    def one(ys, xs) -> None:
        part = stack[:, ys[0]:ys[1], xs[0]:xs[1]]
        if hasattr(part, "compute"):
            part = part.compute(scheduler="sync")
        part = np.asarray(part, dtype=np.float32)
        arr[:, ys[0]:ys[1], xs[0]:xs[1]] = np.clip(part, 0, None, out=part)

    jobs = [dask.delayed(one)(ys, xs) for ys in edges_y for xs in edges_x]
    dask.compute(*jobs, scheduler="threads", num_workers=workers)


def run_pass(task: TilePass, n_y: int, n_x: int, config: dict) -> None:
    """Every tile's task of a pass, as dask tasks (threads, or the cluster's)."""
    import dask

    jobs = [dask.delayed(task, pure=False)(iy, ix) for iy in range(n_y) for ix in range(n_x)]
    dask.compute(*jobs, **config)


__all__ = ["STORE_CHUNK", "TilePass", "open_array", "run_pass", "store_chunk",
           "write_data"]
