"""Seconds of blocked Richardson-Lucy 3D on the CPU, for a checkout given by its path:
the same run on two commits compares the CPU path before and after a change.

A synthetic 71 x 1024 x 1024 stack (the SP8 stack's size) and a field of 6 kernels of
79 x 41 x 41 (its model's), 4 accelerated iterations at the library's blocks and rtol.

    git worktree add /tmp/old COMMIT
    python bench/bench_rl3d_speed.py --src /tmp/old
    python bench/bench_rl3d_speed.py --src .
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchlib import CHECKOUT, use_checkout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", default=str(CHECKOUT),
                    help="the checkout whose src/ is timed")
    ap.add_argument("--iterations", type=int, default=4)
    args = ap.parse_args()
    use_checkout(args.src)
    from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
    from napari_psfspace.core.volume.operator3d import ProductConvolution3D
    rng = np.random.default_rng(0)
    shape = (71, 1024, 1024)
    basis = rng.random((6, 79, 41, 41))
    basis /= basis.sum(axis=(1, 2, 3), keepdims=True)
    grid = np.linspace(0, 1023, 5)
    op = ProductConvolution3D(basis, 0.5 + rng.random((6, 5, 5)), shape=shape,
                              grid=(grid, grid), plane=39)
    stack = rng.poisson(50, shape).astype(np.float32)
    t0 = time.perf_counter()
    res = richardson_lucy_3d(stack, op, n_iter=args.iterations, accelerate=True)
    print(f"{args.src}: {time.perf_counter() - t0:.1f} s for {res.iterations} iterations, "
          f"{res.n_kernels:.3f} kernels a block")


if __name__ == "__main__":
    main()
