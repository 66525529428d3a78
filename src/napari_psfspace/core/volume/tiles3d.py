"""3D deblurring of a volume larger than memory: lateral tiles, each deconvolved alone.

Each tile of ``tile x tile`` pixels (all depths) is read with a margin of ``halo``
pixels on every side, deconvolved with Richardson-Lucy on its own window of the
operator (:meth:`~napari_psfspace.core.volume.operator3d.ProductConvolution3D.cropped`:
the same kernels and maps, no approximation), and its margin dropped. The background
and the starting value are the whole stack's
(:func:`~napari_psfspace.core.volume.deconvolve3d.stack_statistics`), so a tile's result
does not depend on how the rest was cut.

Two doors to the same computation: ``dask.array.map_overlap`` (a dask stack stays
lazy: the result is a dask array to write with ``to_zarr`` or ``compute``; a NumPy
stack is computed, on ``client`` when one is given), and a plain loop over the same
tiles (``use_dask=False``). They agree to float32 rounding (tested). Against the
deconvolution of the whole volume at once, a tile differs near its margin's edge only
(the light of a bead beyond the margin is missing): ``bench/bench_volume.py --tiles``
measures it.
"""

from __future__ import annotations

import numpy as np

from ..common.validate import check_int
from .blocks3d import BLOCK, RTOL
from .deconvolve3d import check_stack, richardson_lucy_3d, stack_statistics
from .operator3d import ProductConvolution3D

#: Default tile size, pixels.
TILE = 512


def default_halo(operator: ProductConvolution3D) -> int:
    """The margin read around a tile: two kernel widths ``2 P`` (the light of a bead
    within one kernel width of the tile, and the reach of that bead's own PSF)."""
    return 2 * operator.kernel_shape[1]


def tile_sizes(n: int, tile: int, halo: int) -> tuple[int, ...]:
    """Tile sizes along an axis of ``n`` pixels: ``tile`` each, the remainder its own
    tile unless it is narrower than the halo (then the last tile takes it: dask's
    ``map_overlap`` would merge it and move the tiles)."""
    sizes = [tile] * (n // tile)
    rest = n - tile * len(sizes)
    if rest:
        if sizes and rest < halo:
            sizes[-1] += rest
        else:
            sizes.append(rest)
    return tuple(sizes)


def _edges(sizes: tuple[int, ...]) -> list[tuple[int, int]]:
    ends = np.cumsum((0,) + sizes)
    return [(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:], strict=True)]


def deblur_tile(data: np.ndarray, operator: ProductConvolution3D, y0: int, x0: int, *,
                n_iter: int, background: float, start: float, block: int | None,
                rtol: float) -> np.ndarray:
    """Richardson-Lucy on one window ``data`` (Z, h, w) whose top-left pixel is
    ``(y0, x0)`` of the operator's field; float32, the window's shape."""
    op = operator.cropped(y0, y0 + data.shape[1], x0, x0 + data.shape[2])
    block = None if block is None else max(min(block, max(data.shape[1:])),
                                           op.kernel_shape[1])
    return richardson_lucy_3d(data, op, n_iter=n_iter, background=background,
                              block=block, rtol=rtol, workers=1, start=start).volume


class TileTask:
    """One tile's deconvolution as dask calls it (a picklable object, so that a
    ``dask.distributed`` cluster can run it): the chunk's index is reliable in
    ``map_overlap``, its ``'array-location'`` is not (a dask bug, dask/dask#11349), so the
    window's origin is the chunk's start less the halo."""

    def __init__(self, operator: ProductConvolution3D, starts_y: tuple[int, ...],
                 starts_x: tuple[int, ...], halo: int, kwargs: dict) -> None:
        self.operator, self.halo, self.kwargs = operator, int(halo), dict(kwargs)
        self.starts_y, self.starts_x = starts_y, starts_x

    def __call__(self, window: np.ndarray, block_info=None) -> np.ndarray:
        _, iy, ix = block_info[0]["chunk-location"]
        return deblur_tile(window.astype(np.float32, copy=False), self.operator,
                           max(self.starts_y[iy] - self.halo, 0),
                           max(self.starts_x[ix] - self.halo, 0), **self.kwargs)


def richardson_lucy_3d_tiled(
    stack,
    operator: ProductConvolution3D,
    *,
    n_iter: int = 50,
    background: float | None = None,
    tile: int = TILE,
    halo: int | None = None,
    block: int | None = BLOCK,
    rtol: float = RTOL,
    use_dask: bool = True,
    client=None,
):
    """Space-varying Richardson-Lucy on lateral tiles (the module's notes).

    Parameters
    ----------
    stack : array_like or dask.array.Array of shape (Z, H, W)
        The blurred volume, image units.
    operator : ProductConvolution3D
    n_iter : int
    background : float, optional
        Default: the stack's (:func:`stack_statistics`).
    tile : int
        Lateral tile size, pixels.
    halo : int, optional
        Margin read around each tile, pixels; default :func:`default_halo`.
    block, rtol
        Within a tile, as :func:`~napari_psfspace.core.volume.deconvolve3d.richardson_lucy_3d`.
    use_dask : bool
        ``dask.array.map_overlap`` (True) or a plain loop over the same tiles.
    client : dask.distributed.Client, optional
        Computes a NumPy stack's tiles on this cluster.

    Returns
    -------
    ndarray of shape (Z, H, W), float32, or a lazy dask array when ``stack`` is one.
    """
    check_stack(stack, operator)
    n_iter = check_int(n_iter, "n_iter", minimum=1)
    p = operator.kernel_shape[1]
    tile = check_int(tile, "tile", minimum=p)
    halo = default_halo(operator) if halo is None else check_int(halo, "halo", minimum=0)
    if halo > tile:
        raise ValueError(f"`halo` must be at most `tile` ({tile} px), got {halo} px")
    b, mean = stack_statistics(stack, background)
    start = max(mean - b, 1e-6)
    kw = dict(n_iter=n_iter, background=b, start=start, block=block, rtol=rtol)
    z, h, w = stack.shape
    rows, cols = tile_sizes(h, tile, halo), tile_sizes(w, tile, halo)
    if not use_dask:
        out = np.empty((z, h, w), np.float32)
        for y0, y1 in _edges(rows):
            for x0, x1 in _edges(cols):
                oy0, ox0 = max(y0 - halo, 0), max(x0 - halo, 0)
                oy1, ox1 = min(y1 + halo, h), min(x1 + halo, w)
                window = np.asarray(stack[:, oy0:oy1, ox0:ox1])
                res = deblur_tile(window, operator, oy0, ox0, **kw)
                out[:, y0:y1, x0:x1] = res[:, y0 - oy0:y1 - oy0, x0 - ox0:x1 - ox0]
        return out

    import dask.array as da

    lazy = isinstance(stack, da.Array)
    chunks = ((z,), rows, cols)
    arr = stack.rechunk(chunks) if lazy else da.from_array(np.asarray(stack), chunks=chunks)
    starts_y, starts_x = np.cumsum((0,) + rows), np.cumsum((0,) + cols)

    one = TileTask(operator, tuple(int(v) for v in starts_y),
                   tuple(int(v) for v in starts_x), halo, kw)
    res = arr.map_overlap(one, depth={0: 0, 1: halo, 2: halo}, boundary="none",
                          dtype=np.float32, trim=True, allow_rechunk=False,
                          meta=np.empty((0, 0, 0), np.float32))
    if lazy:
        return res
    if client is not None:
        return np.asarray(client.compute(res).result())
    from ..common.threads import dask_workers

    # the workers named: from a thread other than the main one (a widget's worker),
    # dask's threads scheduler would otherwise make a pool of cores + 4 threads
    return np.asarray(res.compute(num_workers=dask_workers()))


__all__ = ["TILE", "TileTask", "deblur_tile", "default_halo", "richardson_lucy_3d_tiled",
           "tile_sizes"]
