"""3D deblurring at scale: speed and peak memory on large volumes (2 cores).

The operator is the SP8 stack's learnt 3D model (``../shared/data``; a simulated focus
series where the data are absent), its field stretched over the volume. Each case runs
in a fresh process (its peak resident memory is its own):

- ``rl``: space-varying Richardson-Lucy, 50 iterations on 64 x 1024 x 1024 (bounds:
  <= 5 min, peak <= 4 GB), on lateral blocks with the library's ``rtol``;
- ``si``: the same iteration with one PSF (the centre's; the whole volume, one kernel):
  one space-varying iteration against one shift-invariant iteration, the same run of
  this script (bound 1.6x); ``skimage``: scikit-image's ``richardson_lucy``, the same PSF;
  ``redlionfish``: RedLionfish's CPU path (``method="cpu"``), where it is installed;
- ``rl`` on 64 x 2048 x 2048, 3 iterations, and ``sparse`` (the sparse + smooth
  deblur, 2 power iterations and 2 FISTA iterations) (bound: peak <= 8 GB);
- ``apply``: the exact whole-volume ``apply`` against ``I + 1`` FFT pairs of its padded
  shape (bound 1.5x);
- ``tiles``: the dask path against the loop over the same tiles (same result to float32
  rounding) and against the whole volume at once, on 16 x 1024 x 1024.

    python bench/bench_volume_scale.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchlib import table

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MODEL = Path("/tmp") / "psfspace_bench_sp8_3d.npz"


def model_file() -> str:
    """The SP8 model (learnt once, kept in the temp folder), or a simulated one."""
    from napari_psfspace.core.volume import estimate_operator_3d

    if MODEL.exists():
        return str(MODEL)
    sp8 = DATA / "sp8_confocal_beads" / "sp8_series045_beads_zyx_uint8.tif"
    if sp8.exists():
        from napari_psfspace.io import read_stack

        stack, _ = read_stack(str(sp8))
        op = estimate_operator_3d(stack, psf_radius=22, z_radius=8)
    else:
        from napari_psfspace.core.simulation.focus import simulate_focus_series

        stack, series = simulate_focus_series((768, 768), 40, np.linspace(-0.6, 0.6, 9),
                                              aberrations="strong", seed=1)
        op = estimate_operator_3d(stack, psf_radius=int(series.psf_radius.max()))
    op.save(MODEL)
    return str(MODEL)


def stretched(path: str, depth: int, size: int):
    from napari_psfspace.core.volume import load_operator_3d
    from napari_psfspace.core.volume.operator3d import ProductConvolution3D

    op = load_operator_3d(path)
    gy = op.grid[0] * (size - 1) / max(op.image_shape[1] - 1, 1)
    gx = op.grid[1] * (size - 1) / max(op.image_shape[2] - 1, 1)
    return ProductConvolution3D(op.basis, op.coefficients, shape=(depth, size, size),
                                grid=(gy, gx), plane=depth // 2)


def child(case: str, path: str, depth: int, size: int, n_iter: int) -> dict:
    """One case, in this process; its figures."""
    from napari_psfspace.core.volume.deconvolve3d import (
        iter_richardson_lucy_3d,
        shift_invariant,
    )

    op = stretched(path, depth, size)
    vol = np.random.default_rng(0).poisson(50, (depth, size, size)).astype(np.float32)
    out = {"case": case, "volume": f"{depth}x{size}x{size}", "I": op.n_psf,
           "kernel": "x".join(map(str, op.kernel_shape))}
    if case == "redlionfish":
        from RedLionfishDeconv import RLDeconvolve

        kern = op.kernel_at((size - 1) / 2, (size - 1) / 2).astype(np.float32)
        t0 = time.perf_counter()
        RLDeconvolve.doRLDeconvolutionFromNpArrays(vol, kern, niter=n_iter, method="cpu")
        out["per_iteration"] = (time.perf_counter() - t0) / n_iter
        out["seconds"] = time.perf_counter() - t0
    elif case == "skimage":
        from skimage.restoration import richardson_lucy

        kern = op.kernel_at((size - 1) / 2, (size - 1) / 2).astype(np.float32)
        t0 = time.perf_counter()
        richardson_lucy(vol / vol.max(), kern, num_iter=n_iter, clip=False)
        out["per_iteration"] = (time.perf_counter() - t0) / n_iter
        out["seconds"] = time.perf_counter() - t0
    elif case == "sparse":
        # peak memory of the sparse + smooth deblur: two power iterations and n_iter
        # FISTA iterations are enough to reach it (the arrays are all allocated by then)
        import napari_psfspace.core.volume.fista3d as fista3d

        fista3d.POWER_ITER = 2
        t0 = time.perf_counter()
        res = fista3d.deblur_3d(vol, op, max_iter=n_iter)
        out["seconds"] = time.perf_counter() - t0
        out["per_iteration"] = res.parameters["seconds"] / max(res.iterations + 4, 1)
    elif case == "apply":
        import scipy.fft

        op.apply(vol)  # spectra and maps cached
        t0 = time.perf_counter()
        op.apply(vol)
        out["seconds"] = time.perf_counter() - t0
        x = np.zeros(op.fft_shape(depth), np.float32)
        t0 = time.perf_counter()
        scipy.fft.irfftn(scipy.fft.rfftn(x), s=x.shape)
        out["fft_pairs"] = (op.n_psf + 1) * (time.perf_counter() - t0)
        out["ratio"] = out["seconds"] / out["fft_pairs"]
    else:
        o, block = (shift_invariant(op), None) if case == "si" else (op, 256)
        t0 = time.perf_counter()
        gen = iter_richardson_lucy_3d(vol, o, n_iter=n_iter, background=10.0, block=block)
        next(gen)  # setup
        next(gen)  # first iteration (with the normalisation)
        t1 = time.perf_counter()
        n = 1
        for _ in gen:
            n += 1
        t2 = time.perf_counter()
        out["seconds"] = t2 - t0
        out["per_iteration"] = (t2 - t1) / max(n - 1, 1)
        out["setup_and_first"] = t1 - t0
    out["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    return out


def spawn(case: str, path: str, depth: int, size: int, n_iter: int) -> dict:
    cmd = [sys.executable, __file__, "--child", case, path, str(depth), str(size),
           str(n_iter)]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def tiles(path: str, depth: int, size: int, n_iter: int) -> dict:
    import dask

    from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
    from napari_psfspace.core.volume.tiles3d import default_halo, richardson_lucy_3d_tiled

    op = stretched(path, depth, size)
    vol = np.random.default_rng(0).poisson(50, (depth, size, size)).astype(np.float32)
    t0 = time.perf_counter()
    with dask.config.set(scheduler="threads", num_workers=2):
        lazy = richardson_lucy_3d_tiled(vol, op, n_iter=n_iter, tile=512)
    t_dask = time.perf_counter() - t0
    loop = richardson_lucy_3d_tiled(vol, op, n_iter=n_iter, tile=512, use_dask=False)
    whole = richardson_lucy_3d(vol, op, n_iter=n_iter).volume
    return {"case": "tiles", "volume": f"{depth}x{size}x{size}", "I": op.n_psf,
            "halo": default_halo(op), "seconds": t_dask,
            "dask_vs_loop": float(np.abs(lazy - loop).max() / loop.max()),
            "tiles_vs_whole": float(np.linalg.norm(loop - whole) / np.linalg.norm(whole))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="5 iterations, 1024 only")
    ap.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        case, path, depth, size, n_iter = args.child
        print(json.dumps(child(case, path, int(depth), int(size), int(n_iter))))
        return
    path = model_file()
    n = 5 if args.quick else 50
    rows = [spawn("rl", path, 64, 1024, n), spawn("si", path, 64, 1024, n),
            spawn("skimage", path, 64, 1024, 3), spawn("apply", path, 64, 1024, 1)]
    rl, si, sk = rows[0], rows[1], rows[2]
    rl["vs_si"] = rl["per_iteration"] / si["per_iteration"]
    rl["vs_skimage"] = rl["per_iteration"] / sk["per_iteration"]
    try:  # RedLionfish's CPU path, where it installs (not a dependency)
        import RedLionfishDeconv  # noqa: F401

        lion = spawn("redlionfish", path, 64, 1024, 3)
        rl["vs_redlionfish"] = rl["per_iteration"] / lion["per_iteration"]
        rows.append(lion)
    except ImportError:
        print("RedLionfish is not installed: its row is left out")
    if not args.quick:
        rows.append(spawn("rl", path, 64, 2048, 3))
        rows.append(spawn("sparse", path, 64, 2048, 2))
    print(table(rows, [("case", "s"), ("volume", "s"), ("I", "d"), ("kernel", "s"),
                       ("seconds", ".1f"), ("per_iteration", ".2f"), ("vs_si", ".2f"),
                       ("vs_skimage", ".2f"), ("vs_redlionfish", ".2f"), ("ratio", ".2f"),
                       ("peak_gb", ".2f")]))
    print("bounds: rl 50 iterations on 64x1024x1024 <= 300 s and peak <= 4 GB; vs_si <= "
          "1.6; apply ratio <= 1.5; rl and sparse on 64x2048x2048 peak <= 8 GB")
    t = tiles(path, 16, 1024, 10 if args.quick else 30)
    print(table([t], [("case", "s"), ("volume", "s"), ("I", "d"), ("halo", "d"),
                      ("seconds", ".1f"), ("dask_vs_loop", ".1e"),
                      ("tiles_vs_whole", ".4f")]))


if __name__ == "__main__":
    main()
