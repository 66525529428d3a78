"""Deblur the best-focus slice of every measured set in ``../shared/data`` with its own
learnt operator (issue 12): does it run, stay finite, and what does it call saturated?

    python bench/bench_deblur_all_data.py [--data ../shared/data] [--max-iter 150]

One row per file: shape, dtype, slice, saturated pixels (fitted as lower bounds) and the
level, iterations, whether the result is finite, the sparse part's share of the total,
seconds. A file whose operator cannot be learnt (too few isolated beads) says why.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import tifffile

from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.restore import deblur
from napari_psfspace.io import best_focus_index, read_image


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path,
                    default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--max-iter", type=int, default=150)
    args = ap.parse_args()
    for path in sorted(args.data.rglob("*.tif")):
        with tifffile.TiffFile(path) as tif:
            shape, dtype = tif.series[0].shape, tif.series[0].dtype
        name = path.relative_to(args.data)
        z = None
        if len(shape) == 3:
            stack = np.stack([read_image(path, index=k)[0] for k in range(shape[0])])
            z = best_focus_index(stack)
            image = stack[z]
        else:
            image = read_image(path)[0]
        info = read_image(path, index=0 if len(shape) == 3 else None)[1]
        radius = 0.5 / info.pixel_size if info.pixel_size else 3.0
        try:
            op = estimate_operator(image, psf_radius=radius, holdout=None)
        except ValueError as exc:
            print(f"{name} {shape} {dtype}: no operator: {str(exc).splitlines()[0][:100]}")
            continue
        t0 = time.perf_counter()
        res = deblur(image, op, max_iter=args.max_iter)
        p = res.parameters
        share = res.sparse.sum() / max(float(res.image.sum()), 1e-30)
        print(f"{name} {shape} {dtype}: slice {z}, {p['saturated_pixels']} saturated "
              f"(>= {p['saturation']}), {res.iterations} iterations, finite "
              f"{bool(np.isfinite(res.image).all())}, sparse share {share:.2f}, "
              f"{time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
