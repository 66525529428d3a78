"""Benchmark ProductConvolution.apply / adjoint against raw FFT cost.

Run with ``python bench/bench_apply.py [--size 2304] [--psf 41] [--repeat 7]``.

For each number of basis PSFs ``I`` it reports the median wall time of
``apply`` and ``adjoint`` (after a warm-up call that fills the coefficient-map
and kernel-spectrum caches) and of ``I + 1`` calls of ``scipy.fft.rfft2`` on an
image of the same padded shape, which is the unavoidable FFT work of ``apply``
(I forward transforms + one inverse of the same size). The ratio of the two is
the overhead of everything else (map multiplications, spectral products and
accumulation, cropping); the target is ``ratio <= 1.5``.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import scipy.fft

try:
    from napari_psfspace.core.model.operator import ProductConvolution
except ImportError:  # not installed: use the source tree
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from napari_psfspace.core.model.operator import ProductConvolution


def _interleaved_times_ms(fns, repeat: int) -> list[np.ndarray]:
    """Wall times (ms) of each callable, runs interleaved to share load drift."""
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeat):
        for fn, ts in zip(fns, times, strict=True):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
    return [1e3 * np.array(ts) for ts in times]


def _model(n_psf: int, size: int, psf: int, rng: np.random.Generator) -> ProductConvolution:
    c = psf // 2
    yy, xx = np.mgrid[-c : c + 1, -c : c + 1]
    basis = np.array([np.exp(-(yy**2 + xx**2) / (2.0 * (1.5 + i) ** 2)) for i in range(n_psf)])
    nodes = np.linspace(0, size - 1, 8)
    coef = rng.random((n_psf, 8, 8))
    return ProductConvolution(basis, coef, shape=(size, size), grid=(nodes, nodes))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=2304, help="image side (pixels)")
    parser.add_argument("--psf", type=int, default=41, help="PSF patch size P (odd)")
    parser.add_argument("--repeat", type=int, default=15, help="timed runs (median)")
    parser.add_argument("--workers", type=int, default=2, help="scipy.fft workers")
    parser.add_argument("--n-psf", type=int, nargs="+", default=[1, 3, 5, 8])
    args = parser.parse_args(argv)

    rng = np.random.default_rng(0)
    u = rng.random((args.size, args.size), dtype=np.float32)
    print(
        f"image {args.size}x{args.size} float32, P={args.psf}, workers={args.workers}, "
        f"cpu_count={os.cpu_count()}, numpy {np.__version__}, scipy {scipy.__version__}"
    )
    rows = []
    for n_psf in args.n_psf:
        op = _model(n_psf, args.size, args.psf, rng)
        fshape = op.fft_shape()
        padded = np.zeros(fshape, dtype=np.float32)
        padded[: args.size, : args.size] = u

        def fft_only(n=n_psf, padded=padded):
            for _ in range(n + 1):
                scipy.fft.rfft2(padded, workers=args.workers)

        op.apply(u, workers=args.workers)  # warm-up: fills caches
        op.adjoint(u, workers=args.workers)
        fft_only()
        t_apply, t_fft, t_adj = _interleaved_times_ms(
            [
                lambda op=op: op.apply(u, workers=args.workers),
                fft_only,
                lambda op=op: op.adjoint(u, workers=args.workers),
            ],
            args.repeat,
        )
        # each apply is paired with the FFT baseline timed right after it: the median of
        # the paired ratios is robust to the machine's speed drifting between runs
        ratios = t_apply / t_fft
        rows.append((n_psf, fshape, np.median(t_apply), np.median(t_fft), np.median(ratios),
                     np.percentile(ratios, 25), np.percentile(ratios, 75), np.median(t_adj)))
        del op

    print(f"padded FFT shape: {rows[0][1]}")
    header = (
        f"{'I':>3} | {'apply ms':>9} | {'(I+1) rfft2 ms':>14} | {'ratio':>5} | "
        f"{'ratio p25-p75':>13} | {'adjoint ms':>10}"
    )
    print(header)
    print("-" * len(header))
    for n_psf, _, t_apply, t_fft, ratio, lo, hi, t_adj in rows:
        print(f"{n_psf:>3} | {t_apply:9.1f} | {t_fft:14.1f} | {ratio:5.2f} | "
              f"{lo:6.2f}-{hi:<6.2f} | {t_adj:10.1f}")
    print("ratio: median over runs of apply / (I+1) rfft2 timed back to back (target <= 1.5)")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    scale = 1 if sys.platform == "darwin" else 1024  # bytes on macOS, KiB on Linux
    print(f"peak memory (ru_maxrss): {peak * scale / 2**20:.0f} MiB")


if __name__ == "__main__":
    main()
