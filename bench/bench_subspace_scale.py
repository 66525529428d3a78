"""Time and peak memory of estimate_family against the number of images (issue 11).

    python bench/bench_subspace_scale.py [--ks 10 30 90] [--cache DIR]

Issue 11's scale: 90 simulated 2304 x 2304 images with about 100 beads each, learnt in
<= 10 minutes on 2 cores with peak memory <= 4 GB. The images are simulated once into
``--cache`` (one TIFF each, about 10 MB; a stack of one microscope under hidden
conditions, ``core/simulation/stacks.py``), then each K runs in a fresh process that
learns from the first K files through loaders, so that no process holds the stack: its
peak memory (``ru_maxrss``) is that of the learning, the interpreter and one image per
worker thread. dask's local threaded scheduler, 2 threads.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchlib import table

SHAPE = (2304, 2304)
N_BEADS = 100

CHILD = """
import json, resource, sys, time
import dask
from napari_psfspace.io import stack_loaders
from napari_psfspace.core.family import estimate_family
files, r = json.loads(sys.argv[1]), float(sys.argv[2])
loaders, _ = stack_loaders(files)
dask.config.set(num_workers=2)
t0 = time.perf_counter()
sub = estimate_family(loaders, psf_radius=r, holdout=None)
print(json.dumps({"seconds": time.perf_counter() - t0, "I": sub.n_psf, "J": sub.n_space,
                  "beads": sum(sub.metadata["beads_per_image"]),
                  "peak_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def make_cache(cache: Path, k: int) -> tuple[list[str], float]:
    """Simulate the stack's images that are not yet in ``cache``; their paths and a PSF
    radius (the median of the truths')."""
    from napari_psfspace.core.simulation import simulate_beads
    from napari_psfspace.core.simulation.aberrations import PRESETS, FieldAberrations
    from napari_psfspace.core.simulation.stacks import random_conditions
    from napari_psfspace.io import write_tiff

    cache.mkdir(parents=True, exist_ok=True)
    conds = random_conditions(k, [0, 1])
    base = FieldAberrations(PRESETS["moderate"])
    radius_file = cache / "psf_radius.json"
    radii = json.loads(radius_file.read_text()) if radius_file.exists() else {}
    paths = []
    t0 = time.perf_counter()
    for i, c in enumerate(conds):
        path = cache / f"image_{i:03d}.tif"
        if not path.exists() or str(i) not in radii:
            image, truth = simulate_beads(SHAPE, N_BEADS, aberrations=c.aberrations(base),
                                          seed=np.random.default_rng([0, i]))
            write_tiff(path, image)
            radii[str(i)] = float(truth.psf_radius)
            radius_file.write_text(json.dumps(radii))
            if i % 10 == 9:
                print(f"  simulated {i + 1} images, {time.perf_counter() - t0:.0f} s",
                      flush=True)
        paths.append(str(path))
    return paths, float(np.median([radii[str(i)] for i in range(k)]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ks", type=int, nargs="+", default=[10, 30, 90])
    ap.add_argument("--cache", default="/tmp/psfspace-bench-stack",
                    help="folder for the simulated images (kept between runs)")
    args = ap.parse_args()
    paths, r = make_cache(Path(args.cache), max(args.ks))
    rows = []
    for k in args.ks:
        out = subprocess.run([sys.executable, "-c", CHILD, json.dumps(paths[:k]), str(r)],
                             capture_output=True, text=True, check=True)
        rec = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append({"K": k, **rec})
        print(f"  K={k}: {rec['seconds']:.1f} s, {rec['peak_MB']:.0f} MB", flush=True)
    print(f"\nestimate_subspace on K simulated {SHAPE[0]}x{SHAPE[1]} images of {N_BEADS} "
          f"beads (r = {r:g} px; targets for K = 90: 600 s, 4096 MB)")
    print(table(rows, [("K", "d"), ("beads", "d"), ("I", "d"), ("J", "d"),
                       ("seconds", ".1f"), ("peak_MB", ".0f")]))


if __name__ == "__main__":
    main()
