"""Seconds of the deblurring paths the device seam touches, on the CPU, for a checkout given
by its path: the same run on two commits compares the CPU path before and after a change.

The 2-D operator at 2048 x 2048 with 8 kernels of 41 x 41 (apply, adjoint, the fused
data gradient: median of ``--repeat``), the 2-D deblur (FISTA, a fixed number of
iterations, no polish), the 3D operator on the whole volume (16 x 512 x 512, 4 kernels of
17 x 45 x 45) and the 3D sparse + smooth deblur (a fixed number of iterations).

    git worktree add /tmp/old COMMIT
    python bench/bench_seam_cpu.py --src /tmp/old
    python bench/bench_seam_cpu.py --src .
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchlib import CHECKOUT, use_checkout


def _median(fn, repeat: int) -> float:
    fn()  # caches (spectra, maps) and FFT plans, once
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", default=str(CHECKOUT),
                    help="the checkout whose src/ is timed")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--iterations", type=int, default=20)
    args = ap.parse_args()
    use_checkout(args.src)
    import napari_psfspace
    from napari_psfspace.core.model.operator import ProductConvolution
    from napari_psfspace.core.restore.deconvolve import deblur
    from napari_psfspace.core.volume.fista3d import deblur_3d
    from napari_psfspace.core.volume.operator3d import ProductConvolution3D
    rng = np.random.default_rng(0)
    n = 2048
    basis = rng.random((8, 41, 41))
    basis /= basis.sum(axis=(1, 2), keepdims=True)
    g = np.linspace(0, n - 1, 6)
    op = ProductConvolution(basis, 0.5 + rng.random((8, 6, 6)), shape=(n, n), grid=(g, g))
    u = rng.random((n, n)).astype(np.float32)
    y = rng.poisson(op.apply(u * (rng.random((n, n)) < 1e-3) * 1e3) + 20).astype(np.float32)
    rows = [("2-D apply", _median(lambda: op.apply(u), args.repeat)),
            ("2-D adjoint", _median(lambda: op.adjoint(u), args.repeat)),
            ("2-D data_gradient", _median(lambda: op.data_gradient(u, y), args.repeat))]
    kw = {"max_iter": args.iterations, "tol": 1e-12, "polish": False}
    if "device" in deblur.__code__.co_varnames:
        kw["device"] = "cpu"
    t0 = time.perf_counter()
    res = deblur(y, op, **kw)
    rows.append((f"2-D deblur, {res.iterations} its", time.perf_counter() - t0))

    shape = (16, 512, 512)
    b3 = rng.random((4, 17, 45, 45))
    b3 /= b3.sum(axis=(1, 2, 3), keepdims=True)
    g3 = np.linspace(0, 511, 4)
    op3 = ProductConvolution3D(b3, 0.5 + rng.random((4, 4, 4)), shape=shape, grid=(g3, g3),
                               plane=8)
    v = rng.random(shape).astype(np.float32)
    rows += [("3D apply (whole)", _median(lambda: op3.apply(v), max(2, args.repeat // 2))),
             ("3D adjoint (whole)", _median(lambda: op3.adjoint(v), max(2, args.repeat // 2)))]
    stack = rng.poisson(op3.apply(v * (rng.random(shape) < 1e-3) * 1e3) + 20).astype(
        np.float32)
    kw3 = {"max_iter": args.iterations // 2, "tol": 0.0}
    if "device" in deblur_3d.__code__.co_varnames:
        kw3["device"] = "cpu"
    t0 = time.perf_counter()
    res3 = deblur_3d(stack, op3, **kw3)
    rows.append((f"3D deblur_3d, {res3.iterations} its", time.perf_counter() - t0))
    print(f"{args.src} ({napari_psfspace.__file__})")
    width = max(len(name) for name, _ in rows)
    for name, sec in rows:
        print(f"{name.ljust(width)} | {sec:8.3f} s")


if __name__ == "__main__":
    main()
