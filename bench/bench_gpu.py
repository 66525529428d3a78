"""The deblurring on the GPU (CuPy) against the CPU path, on one machine, in one run.

For synthetic volumes blurred by a field of I = 4 kernels of 17 x 45 x 45 voxels:

* one Richardson-Lucy 3D iteration at 64 x 1024 x 1024 and 64 x 2048 x 2048: seconds on
  the GPU (the mean of the iterations after the first), on the CPU (one iteration, all
  cores), and the floor: ``I + 1`` pairs of rfftn + irfftn of the padded shape, timed on
  the GPU in the same run;
* the relative l2 difference of 10 iterations' result from the CPU's;
* the device's peak memory during the run (CuPy's pool, what the arrays held);
* a 256 x 2048 x 2048 volume: its plan (the blocks, where the volumes live), its peak
  memory, and that it ran;
* the sparse + smooth deblurs: ``deblur_3d`` at 64 x 2048 x 2048 (the same field) and the
  2-D ``deblur`` at 2048 x 2048 (I = 12 kernels of 41 x 41), a fixed number of
  iterations each (no stopping rule, no polish) on the GPU and on the CPU: the seconds of
  the whole call and of an iteration, and the relative l2 difference of the results.

Imports only the core (no dask, napari or magicgui): it runs on a bare GPU machine.

    python bench/bench_gpu.py [--sizes 1024 2048] [--big] [--cpu-iterations 10]
    python bench/bench_gpu.py --small     # a small smoke run (CPU only where no GPU)
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from benchlib import table  # stdlib only; it puts src on the path
from napari_psfspace.core.common.device import array_module, gpu_status
from napari_psfspace.core.model.operator import ProductConvolution
from napari_psfspace.core.restore.deconvolve import deblur
from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
from napari_psfspace.core.volume.device_plan import plan_on_device
from napari_psfspace.core.volume.fista3d import deblur_3d
from napari_psfspace.core.volume.operator3d import ProductConvolution3D


def operator(shape, kernel=(17, 45, 45), n=4, seed=0) -> ProductConvolution3D:
    """A smooth field of ``n`` Gaussian-like kernels over a 5 x 5 grid."""
    rng = np.random.default_rng(seed)
    k, p, _ = kernel
    z, y, x = np.meshgrid(np.arange(k) - k // 2, np.arange(p) - p // 2,
                          np.arange(p) - p // 2, indexing="ij")
    basis = []
    for i in range(n):
        s = 2.0 + i
        g = np.exp(-(y ** 2 + x ** 2) / (2 * s ** 2) - z ** 2 / (2 * (2 * s) ** 2))
        basis.append(g / g.sum())
    gy, gx = np.linspace(0, shape[1] - 1, 5), np.linspace(0, shape[2] - 1, 5)
    coef = 0.2 + rng.random((n, 5, 5))
    return ProductConvolution3D(np.array(basis), coef / coef.sum(0), shape=shape,
                                grid=(gy, gx), plane=k // 2)


def volume(op: ProductConvolution3D, seed=1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    obj = np.zeros(op.image_shape, np.float32)
    n = obj.size // 2000
    obj[tuple(rng.integers(0, s, n) for s in op.image_shape)] = rng.uniform(500, 5000, n)
    return rng.poisson(np.clip(op.apply(obj), 0, None) + 20).astype(np.float32)


class Peak:
    """The peak of the bytes CuPy's pool lends to arrays (a memory hook)."""

    def __init__(self):
        import cupy

        class Hook(cupy.cuda.MemoryHook):
            name = "peak"

            def __init__(self):
                self.now = self.peak = 0

            def malloc_postprocess(self, **kw):
                self.now += kw["mem_size"]
                self.peak = max(self.peak, self.now)

            def free_postprocess(self, **kw):
                self.now -= kw["mem_size"]

        self.hook = Hook()

    def __enter__(self):
        self.hook.__enter__()
        return self.hook

    def __exit__(self, *exc):
        self.hook.__exit__(*exc)


def fft_floor(am, op, depth: int) -> float:
    """Seconds of ``I + 1`` rfftn + irfftn pairs of the whole field's padded shape."""
    plan = plan_on_device(op, depth, am.free_bytes())
    k, p, _ = op.kernel_shape
    import scipy.fft

    fz = scipy.fft.next_fast_len(depth + k // 2, real=True)
    fl = scipy.fft.next_fast_len(plan.block + p - 1, real=True)
    x = am.xp.zeros((fz, fl, fl), np.float32)
    am.irfftn(am.rfftn(x), s=x.shape)  # plans made
    am.synchronize()
    t0 = time.perf_counter()
    for _ in range(5):
        am.irfftn(am.rfftn(x), s=x.shape)
    am.synchronize()
    del x
    return (time.perf_counter() - t0) / 5 * (op.n_psf + 1)


def per_iteration(stack, op, device, n_iter) -> tuple[float, object]:
    """Seconds an iteration after the first (``n_iter`` >= 2), and the result."""
    times = []
    last = [time.perf_counter()]

    def on(rec):
        if rec.stage == "iteration" and rec.message.startswith("iteration") and \
                ", change" in rec.message:
            now = time.perf_counter()
            times.append(now - last[0])
            last[0] = now

    res = richardson_lucy_3d(stack, op, n_iter=n_iter, device=device, progress=on)
    return float(np.mean(times[1:] if len(times) > 1 else times)), res


def operator_2d(size: int, n: int = 12, p: int = 41, seed=0) -> ProductConvolution:
    """A smooth field of ``n`` Gaussian kernels of ``p x p`` over a 6 x 6 grid."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:p, :p] - p // 2
    basis = [np.exp(-(y ** 2 + x ** 2) / (2 * (1.5 + 0.4 * i) ** 2)) for i in range(n)]
    basis = np.array([b / b.sum() for b in basis])
    g = np.linspace(0, size - 1, 6)
    coef = 0.2 + rng.random((n, 6, 6))
    return ProductConvolution(basis, coef / coef.sum(0), shape=(size, size), grid=(g, g))


def image_2d(op: ProductConvolution, seed=1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    obj = np.zeros(op.image_shape, np.float32)
    n = obj.size // 2000
    obj[tuple(rng.integers(0, s, n) for s in op.image_shape)] = rng.uniform(500, 5000, n)
    return rng.poisson(np.clip(op.apply(obj), 0, None) + 20).astype(np.float32)


def timed_deblur(fn, data, op, device, n_iter, **kw) -> tuple[dict, object]:
    """The whole call's seconds and an iteration's (the mean after the first), and the
    result, of a sparse + smooth deblur run for exactly ``n_iter`` iterations."""
    stamps = []

    def on(rec):
        if rec.stage == "deblur" and "iteration" in rec.message:
            stamps.append(time.perf_counter())

    t0 = time.perf_counter()
    res = fn(data, op, max_iter=n_iter, tol=0.0 if fn is deblur_3d else 1e-30,
             device=device, progress=on, **kw)
    total = time.perf_counter() - t0
    steps = np.diff(stamps)
    return {"total_s": total, "iter_s": float(np.mean(steps)) if len(steps) else None}, res


def deblur_rows(size2d: int, shape3d: tuple, n_iter: int, ok: bool) -> list[dict]:
    """The 2-D deblur and deblur_3d, CPU and (where there is one) GPU."""
    rows = []
    for name, fn, op, kw in (("deblur 2-D", deblur, operator_2d(size2d), {"polish": False}),
                             ("deblur_3d", deblur_3d, operator(shape3d), {})):
        data = image_2d(op) if fn is deblur else volume(op)
        shape = "x".join(map(str, op.image_shape))
        cpu_t, cpu = timed_deblur(fn, data, op, "cpu", n_iter, **kw)
        row = {"what": name, "shape": shape, "its": cpu.iterations,
               "cpu_total_s": cpu_t["total_s"], "cpu_iter_s": cpu_t["iter_s"]}
        if ok:
            with Peak() as peak:
                gpu_t, gpu = timed_deblur(fn, data, op, "gpu", n_iter, **kw)
            a = gpu.image if fn is deblur else gpu.volume
            b = cpu.image if fn is deblur else cpu.volume
            row.update(gpu_total_s=gpu_t["total_s"], gpu_iter_s=gpu_t["iter_s"],
                       speedup=cpu_t["iter_s"] / gpu_t["iter_s"],
                       rel_l2=float(np.linalg.norm(a - b) / np.linalg.norm(b)),
                       peak_GiB=peak.peak / 2**30)
        rows.append(row)
        print(table(rows[-1:], DEBLUR_COLUMNS), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", type=int, default=[1024, 2048])
    ap.add_argument("--depth", type=int, default=64)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--cpu-iterations", type=int, default=10,
                    help="CPU iterations for the difference (0: time one only)")
    ap.add_argument("--big", action="store_true", help="also 256 x 2048 x 2048")
    ap.add_argument("--small", action="store_true", help="a smoke run: 16 x 256 x 256")
    ap.add_argument("--deblur-iterations", type=int, default=10,
                    help="iterations of each sparse + smooth deblur (0: none run)")
    args = ap.parse_args()
    ok, why = gpu_status()
    print(f"machine: {platform.node()}, {platform.processor() or platform.machine()}; "
          f"GPU: {'yes' if ok else 'no (' + why + ')'}")
    if ok:
        import cupy

        props = cupy.cuda.runtime.getDeviceProperties(0)
        print(f"device: {props['name'].decode()}, "
              f"{props['totalGlobalMem'] / 2**30:.0f} GiB; CuPy {cupy.__version__}")
    sizes, depth = ([256], 16) if args.small else (args.sizes, args.depth)
    rows = []
    for size in sizes:
        op = operator((depth, size, size))
        stack = volume(op)
        row = {"shape": f"{depth}x{size}x{size}", "I": op.n_psf}
        n_cpu = max(args.cpu_iterations, 2)
        row["cpu_s"], cpu = per_iteration(stack, op, "cpu", n_cpu)
        if ok:
            am = array_module("gpu")
            row["floor_s"] = fft_floor(am, op, depth)
            with Peak() as peak:
                row["gpu_s"], gpu = per_iteration(stack, op, "gpu", args.iterations)
            row["peak_GiB"] = peak.peak / 2**30
            row["block"] = gpu.block
            row["vs_floor"] = row["gpu_s"] / row["floor_s"]
            row["speedup"] = row["cpu_s"] / row["gpu_s"]
            if args.cpu_iterations >= 2 and args.iterations == n_cpu:
                row["rel_l2"] = float(np.linalg.norm(gpu.volume - cpu.volume)
                                      / np.linalg.norm(cpu.volume))
        rows.append(row)
        print(table(rows[-1:], COLUMNS), flush=True)
    if ok and args.big:
        op = operator((256, 2048, 2048))
        am = array_module("gpu")
        plan = plan_on_device(op, 256, am.free_bytes())
        stack = volume(op)
        with Peak() as peak:
            t, res = per_iteration(stack, op, "gpu", 2)
        rows.append({"shape": "256x2048x2048", "I": op.n_psf, "gpu_s": t,
                     "peak_GiB": peak.peak / 2**30, "block": res.block})
        print(f"256x2048x2048: block {plan.block}, volumes on the device: "
              f"{plan.volumes_on_device}; ran {res.iterations} iterations")
    deblurs = []
    if args.deblur_iterations:
        size2d, shape3d = (256, (16, 256, 256)) if args.small else \
            (2048, (depth, 2048, 2048))
        deblurs = deblur_rows(size2d, shape3d, args.deblur_iterations, ok)
    print("\nRichardson-Lucy 3D, one iteration (I = 4 kernels of 17 x 45 x 45)")
    print(table(rows, COLUMNS))
    if deblurs:
        print(f"\nSparse + smooth deblurs, {args.deblur_iterations} iterations each "
              "(2-D: I = 12 kernels of 41 x 41; 3D: the field above)")
        print(table(deblurs, DEBLUR_COLUMNS))


DEBLUR_COLUMNS = [("what", "s"), ("shape", "s"), ("its", "d"), ("gpu_total_s", ".2f"),
                  ("gpu_iter_s", ".4f"), ("cpu_total_s", ".1f"), ("cpu_iter_s", ".3f"),
                  ("speedup", ".1f"), ("rel_l2", ".1e"), ("peak_GiB", ".1f")]
COLUMNS = [("shape", "s"), ("I", "d"), ("block", "d"), ("gpu_s", ".4f"), ("floor_s", ".4f"),
           ("vs_floor", ".2f"), ("cpu_s", ".2f"), ("speedup", ".1f"), ("rel_l2", ".1e"),
           ("peak_GiB", ".1f")]


if __name__ == "__main__":
    main()
