"""Are the CPU results of two checkouts bit for bit the same? The 2-D deblur (defaults,
polish included), the 3D sparse + smooth deblur and accelerated Richardson-Lucy 3D on small
seeded scenes, run by each checkout in its own process, compared array by array.

    git worktree add /tmp/old COMMIT
    python bench/bench_seam_identical.py /tmp/old .
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

RUN = r'''
import sys
src, out = sys.argv[1], sys.argv[2]
sys.path.insert(0, src + "/src")
import numpy as np
import napari_psfspace
assert napari_psfspace.__file__.startswith(src), napari_psfspace.__file__
from napari_psfspace.core.model.operator import ProductConvolution
from napari_psfspace.core.restore.deconvolve import deblur
from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
from napari_psfspace.core.volume.fista3d import deblur_3d
from napari_psfspace.core.volume.operator3d import ProductConvolution3D
rng = np.random.default_rng(0)
basis = rng.random((4, 15, 15))
basis /= basis.sum(axis=(1, 2), keepdims=True)
g = np.linspace(0, 255, 4)
op = ProductConvolution(basis, 0.5 + rng.random((4, 4, 4)), shape=(256, 256), grid=(g, g))
truth = (rng.random((256, 256)) < 0.003) * rng.uniform(200, 500, (256, 256))
y = rng.poisson(op.apply(truth) + 20).astype(np.float32)
d2 = deblur(y, op, max_iter=200)
b3 = rng.random((3, 9, 15, 15))
b3 /= b3.sum(axis=(1, 2, 3), keepdims=True)
g3 = np.linspace(0, 127, 3)
op3 = ProductConvolution3D(b3, 0.5 + rng.random((3, 3, 3)), shape=(8, 128, 128),
                           grid=(g3, g3), plane=4)
t3 = (rng.random(op3.shape) < 0.002) * rng.uniform(200, 500, op3.shape)
s3 = rng.poisson(op3.apply(t3) + 10).astype(np.float32)
d3 = deblur_3d(s3, op3, max_iter=20, grid_step=32)
r3 = richardson_lucy_3d(s3, op3, n_iter=8, accelerate=True)
np.savez(out, deblur_2d=d2.image, deblur_3d=d3.volume, rl_3d=r3.volume,
         deblur_2d_iterations=d2.iterations, deblur_3d_iterations=d3.iterations)
'''


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="one checkout")
    ap.add_argument("b", help="the other")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        got = []
        for i, src in enumerate((args.a, args.b)):
            out = Path(tmp) / f"{i}.npz"
            subprocess.run([sys.executable, "-c", RUN, str(Path(src).resolve()), str(out)],
                           check=True)
            got.append(np.load(out))
        print(f"{'result':22} | identical | max |a - b|")
        for key in got[0].files:
            a, b = got[0][key], got[1][key]
            print(f"{key:22} | {str(np.array_equal(a, b)):9} | "
                  f"{float(np.abs(a.astype(float) - b.astype(float)).max()):.3g}")


if __name__ == "__main__":
    main()
