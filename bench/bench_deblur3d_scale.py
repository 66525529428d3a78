"""Deblurring volumes larger than memory: seconds per iteration, peak memory, the tiles'
overhead and the cost against shift-invariant Richardson-Lucy (RedLionfish, scikit-image).

    python bench/bench_deblur3d_scale.py [--sizes 32x768 64x1024 35x2048 64x2048] [--iterations 5]
                                         [--memory 4GB] [--large 128x4096 --large-memory 2GB]

Each run is a fresh process (its peak resident memory, ``ru_maxrss``, is its own):

- ``memory``: ``richardson_lucy_3d`` on the whole volume in memory (blocks of 256 px, the
  library's ``rtol``);
- ``tiles``: ``deblur_to_store`` from a TIFF to an OME-Zarr, tiles that exchange their
  margins every iteration, tiles and threads from ``--memory`` (the whole volume's
  result: its largest difference from ``memory`` is printed);
- ``RedLionfish``: its CPU path (``doRLDeconvolutionFromNpArrays(method="cpu")``), one PSF
  (the field's centre), when the package is installed;
- ``scikit-image``: ``restoration.richardson_lucy`` with that PSF, on the first size only
  (the slowest).

The field: 4 kernels of 21 x 31 x 31 voxels (astigmatic Gaussians whose widths vary over
a 4 x 4 grid), the stack Poisson noise about a constant with sparse bright points (the
iterations' cost does not depend on the content). An iteration with ``k`` kernels a
block takes ``2 (k + 1)`` FFTs against 4 for one PSF: the ``floor`` column is
``(k + 1) / 2`` times RedLionfish's time, and ``x floor`` how far above it the
space-varying run is.

``--scaling``: one stack of 8 tiles deblurred on a ``dask.distributed`` ``LocalCluster``
of 1 and of 2 worker processes, one thread each (a tile's FFTs run on one core): the
seconds an iteration, and the speed-up.

``--large``: a stack of that size, written as a uint16 OME-Zarr a plane at a time (never
whole in memory), deblurred by ``psfspace deblur3d --memory`` (``--large-memory``) into an
OME-Zarr: its peak memory against the budget, and its seconds per iteration.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchlib import SRC, table

KERNEL = (21, 31, 31)
N_PSF = 4

CHILD = r"""
import json, resource, sys, time
sys.path.insert(0, {src!r})
sys.path.insert(0, {bench!r})
import numpy as np
from bench_deblur3d_scale import make_operator
kind, path, n_iter, extra = {kind!r}, {path!r}, {n_iter}, {extra!r}
stack = None if kind in ("tiles", "cli") else np.load(path, mmap_mode="r")
op = make_operator(extra["shape"])
t0 = time.perf_counter(); out = {{}}
if kind == "memory":
    from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
    res = richardson_lucy_3d(np.asarray(stack), op, n_iter=n_iter)
    np.save(extra["result"], res.volume)
    out["kernels"] = res.n_kernels
elif kind == "tiles":
    from napari_psfspace.deblur_store import deblur_to_store
    run = deblur_to_store(path, op, extra["result"], n_iter=n_iter, memory=extra["memory"])
    out["tile"], out["workers"] = run.tile, extra.get("workers")
elif kind == "redlionfish":
    from RedLionfishDeconv import doRLDeconvolutionFromNpArrays
    psf = op.kernel_at((op.image_shape[1] - 1) / 2, (op.image_shape[2] - 1) / 2)
    doRLDeconvolutionFromNpArrays(np.asarray(stack, np.float32), psf, niter=n_iter,
                                  method="cpu")
elif kind == "skimage":
    from skimage.restoration import richardson_lucy
    psf = op.kernel_at((op.image_shape[1] - 1) / 2, (op.image_shape[2] - 1) / 2)
    richardson_lucy(np.asarray(stack, np.float32), psf / psf.sum(), num_iter=n_iter,
                    clip=False)
out["seconds"] = time.perf_counter() - t0
out["maxrss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
print(json.dumps(out))
"""


def make_operator(shape):
    """The bench's field (module docstring) for a stack of ``shape`` (Z, H, W)."""
    from napari_psfspace.core.volume.operator3d import ProductConvolution3D

    k, p, _ = KERNEL
    z, y, x = np.meshgrid(np.arange(k) - k // 2, np.arange(p) - p // 2,
                          np.arange(p) - p // 2, indexing="ij")
    basis = []
    for sy, sx, sz in ((1.5, 1.5, 3.0), (2.5, 1.2, 3.0), (1.2, 2.5, 3.0), (2.0, 2.0, 5.0)):
        g = np.exp(-0.5 * ((y / sy) ** 2 + (x / sx) ** 2 + (z / sz) ** 2))
        basis.append(g / g.sum())
    rng = np.random.default_rng(0)
    coef = 0.2 + rng.random((N_PSF, 4, 4))
    coef /= coef.sum(axis=0, keepdims=True)
    gy, gx = np.linspace(0, shape[1] - 1, 4), np.linspace(0, shape[2] - 1, 4)
    return ProductConvolution3D(np.array(basis), coef, shape=tuple(shape), grid=(gy, gx),
                                plane=shape[0] // 2)


def make_stack(shape, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    stack = rng.poisson(20.0, shape).astype(np.uint16)
    n = int(np.prod(shape) // 20000)
    idx = tuple(rng.integers(0, s, n) for s in shape)
    stack[idx] += rng.integers(200, 2000, n).astype(np.uint16)
    return stack


def write_large_ome_zarr(path: Path, shape) -> None:
    """A uint16 OME-Zarr of ``shape``, written a plane at a time."""
    from napari_psfspace.ome_zarr import create_ome_zarr

    arr = create_ome_zarr(path, shape, dtype="uint16", voxel_size=(0.2, 0.1, 0.1),
                          chunk=1024)
    for z in range(shape[0]):
        arr[z] = make_stack((1, *shape[1:]), seed=z)[0]


def child(kind, path, n_iter, **extra) -> dict:
    code = CHILD.format(src=str(SRC), bench=str(Path(__file__).parent), kind=kind,
                        path=str(path), n_iter=n_iter, extra=extra)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if res.returncode:
        return {"error": res.stderr.strip().splitlines()[-1][:120]}
    return json.loads(res.stdout.strip().splitlines()[-1])


def scaling(shape, tile, n_iter) -> None:
    """Seconds an iteration on a LocalCluster of 1 and 2 single-threaded workers."""
    from distributed import Client, LocalCluster

    from napari_psfspace.core.volume.exchange3d import richardson_lucy_3d_exchange

    op, stack = make_operator(shape), make_stack(shape).astype(np.float32)
    n_tiles = -(-shape[1] // tile) * -(-shape[2] // tile)
    rows, ref = [], None
    for n in (1, 2):
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            richardson_lucy_3d_exchange(stack[:, :tile, :tile], make_operator(
                (shape[0], tile, tile)), n_iter=1, tile=tile, client=client)  # warm up
            t0 = time.perf_counter()
            out = richardson_lucy_3d_exchange(stack, op, n_iter=n_iter, tile=tile,
                                              client=client)
            secs = (time.perf_counter() - t0) / n_iter
        ref = out if ref is None else ref
        rows.append({"workers": n, "s_it": secs, "speedup": rows[0]["s_it"] / secs
                     if rows else 1.0, "max_diff": float(np.abs(out - ref).max() / ref.max())})
    print(f"\ndask LocalCluster, {shape[0]} x {shape[1]} x {shape[2]}, {n_tiles} tiles of "
          f"{tile} px, {n_iter} iterations, one thread a worker")
    print(table(rows, [("workers", "d"), ("s_it", ".2f"), ("speedup", ".2f"),
                       ("max_diff", ".1e")]))


def main() -> None:
    from dask.utils import parse_bytes

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="*", default=["32x768", "64x1024", "35x2048", "64x2048"],
                    help="stacks DEPTHxSIDE (none: only --large)")
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--memory", default="4GB", help="the tiled runs' budget")
    ap.add_argument("--scaling", help="a stack DEPTHxHEIGHTxWIDTH run on 1 and 2 dask "
                    "workers, in tiles of --scaling-tile")
    ap.add_argument("--scaling-tile", type=int, default=512)
    ap.add_argument("--large", help="a stack DEPTHxSIDE far larger than --large-memory")
    ap.add_argument("--large-memory", default="2GB")
    args = ap.parse_args()
    rows = []
    try:
        import RedLionfishDeconv  # noqa: F401
        peers = ["redlionfish"]
    except ImportError:
        peers = []
        print("RedLionfish is not installed (pip install redlionfish): its column is empty",
              file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for i, size in enumerate(args.sizes):
            depth, side = (int(v) for v in size.split("x"))
            shape = (depth, side, side)
            stack = make_stack(shape)
            npy, tif = tmp / f"s{i}.npy", tmp / f"s{i}.tif"
            np.save(npy, stack)
            import tifffile

            tifffile.imwrite(tif, stack, imagej=True)
            del stack
            n = args.iterations
            mem = child("memory", npy, n, shape=shape, result=str(tmp / "mem.npy"))
            tiles = child("tiles", tif, n, shape=shape, result=str(tmp / f"t{i}.zarr"),
                          memory=float(parse_bytes(args.memory)))
            row = {"stack": f"{depth} x {side}^2", "iterations": n,
                   "kernels": mem.get("kernels", float("nan")),
                   "memory_s_it": mem.get("seconds", np.nan) / n,
                   "memory_GB": mem.get("maxrss_gb", np.nan),
                   "tiles_s_it": tiles.get("seconds", np.nan) / n,
                   "tiles_GB": tiles.get("maxrss_gb", np.nan), "tile": tiles.get("tile", 0)}
            row["tiles/memory"] = row["tiles_s_it"] / row["memory_s_it"]
            if "error" not in tiles and "error" not in mem:
                from napari_psfspace.io import read_stack

                whole = np.load(tmp / "mem.npy")
                got = read_stack(tmp / f"t{i}.zarr")[0]
                row["max_diff"] = float(np.abs(got - whole).max() / whole.max())
                del whole, got
            for peer in peers + (["skimage"] if i == 0 else []):
                r = child(peer, npy, n, shape=shape)
                row[f"{peer}_s_it"] = r.get("seconds", np.nan) / n
            if "redlionfish_s_it" in row:
                floor = (row["kernels"] + 1) / 2 * row["redlionfish_s_it"]
                row["x_floor"] = row["memory_s_it"] / floor
                row["x_redlionfish"] = row["memory_s_it"] / row["redlionfish_s_it"]
            if "skimage_s_it" in row:
                row["x_skimage"] = row["memory_s_it"] / row["skimage_s_it"]
            for name, r in (("memory", mem), ("tiles", tiles)):
                if "error" in r:
                    row["note"] = f"{name}: {r['error']}"
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
        if rows:
            print(f"Richardson-Lucy 3D, {args.iterations} iterations, 2-core machine; tiles "
                  f"from a budget of {args.memory}")
            print(table(rows, [("stack", "s"), ("kernels", ".2f"), ("memory_s_it", ".2f"),
                           ("memory_GB", ".2f"), ("tiles_s_it", ".2f"), ("tiles_GB", ".2f"),
                               ("tile", "d"), ("tiles/memory", ".2f"),
                               ("max_diff", ".1e"), ("redlionfish_s_it", ".2f"),
                               ("x_redlionfish", ".2f"), ("x_floor", ".2f"),
                               ("skimage_s_it", ".2f"), ("x_skimage", ".2f")]))
        if args.scaling:
            scaling(tuple(int(v) for v in args.scaling.split("x")), args.scaling_tile,
                    args.iterations)
        if args.large:
            depth, side = (int(v) for v in args.large.split("x"))
            shape = (depth, side, side)
            src = tmp / "large.zarr"
            t0 = time.perf_counter()
            write_large_ome_zarr(src, shape)
            made = time.perf_counter() - t0
            make_operator(shape).save(tmp / "large_model.npz")
            code = (f"import resource, sys, time; sys.path.insert(0, {str(SRC)!r}); "
                    "from napari_psfspace.cli import main; t0 = time.perf_counter(); "
                    f"rc = main(['deblur3d', {str(src)!r}, '--model', "
                    f"{str(tmp / 'large_model.npz')!r}, '-o', {str(tmp / 'out.zarr')!r}, "
                    f"'--memory', {args.large_memory!r}, '--iterations', "
                    f"'{args.iterations}', '-q']); "
                    "print(rc, time.perf_counter() - t0, "
                    "resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20)")
            res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
            last = res.stdout.strip().splitlines()[-1].split() if res.stdout.strip() else []
            gb = float(np.prod(shape)) * 4 / 1e9
            print(f"\nlarger than memory: {depth} x {side}^2 uint16 OME-Zarr ({gb:.1f} GB as "
                  f"float32; written in {made:.0f} s), psfspace deblur3d --memory "
                  f"{args.large_memory}, {args.iterations} iterations")
            if len(last) == 3 and last[0] == "0":
                from napari_psfspace.ome_zarr import read_ome_zarr

                secs, peak = float(last[1]), float(last[2])
                print(f"  {secs / args.iterations:.1f} s an iteration (with the output "
                      f"written), peak resident memory {peak:.2f} GiB against a budget of "
                      f"{parse_bytes(args.large_memory) / 2**30:.2f} GiB")
                # every chunk written (the reader refuses a missing one), and finite
                out = read_ome_zarr(tmp / "out.zarr", lazy=True)[0]
                mid = np.asarray(out[depth // 2])
                print(f"  output complete, {out.shape}; middle plane finite "
                      f"{bool(np.isfinite(mid).all())}, mean {float(mid.mean()):.2f} "
                      f"(input {float(make_stack((1, side, side), seed=depth // 2).mean()):.2f})")
            else:
                print("  failed: " + (res.stderr.strip().splitlines() or ["?"])[-1][:200])


if __name__ == "__main__":
    main()
