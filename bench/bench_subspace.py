"""A family of operators against one image at a time (issue 11).

    python bench/bench_subspace.py [--quick]

Stacks from ``core/simulation/stacks.py`` (K images of one microscope, each under a hidden
focus shift, tilt and spherical drift; moderate field aberrations; 384 x 384; bead
photons x0.2 of the default, i.e. noisy beads). For each stack: the mean per-image
PSF-field error (bench_accuracy's aligned error, 4 x 4 grid) of ``subspace.operator(k)``
and of ``estimate_operator`` on each image alone, their ratio (issue 11 asks for <= 0.6,
and <= 0.5 on few-bead stacks), the sizes I and J chosen (or set), and the time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchlib import table
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.stacks import simulate_stack

LOW = (4e3, 1.2e4)


def row(k, n_beads, seed, n_psf=None, n_space=None, alone=None, photons=1.0):
    amplitude = (LOW[0] * photons, LOW[1] * photons)
    images, truths, _ = simulate_stack(k, (384, 384), n_beads, seed=seed,
                                       amplitude=amplitude)
    r = int(np.median([t.psf_radius for t in truths]))
    t0 = time.perf_counter()
    sub = estimate_family(images, psf_radius=r, n_psf=n_psf, n_space=n_space)
    seconds = time.perf_counter() - t0
    pooled = np.mean([np.mean(grid_errors(sub.operator(i), truths[i], n=4))
                      for i in range(sub.n_images)])
    if alone is None:
        alone = np.mean([np.mean(grid_errors(estimate_operator(im, psf_radius=r), t, n=4))
                         for im, t in zip(images, truths, strict=True)])
    return {"K": k, "beads": n_beads, "seed": seed, "photons": 0.2 * photons,
            "I": sub.n_psf, "J": sub.n_space,
            "subspace": float(pooled), "alone": float(alone),
            "ratio": float(pooled / alone), "seconds": seconds}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="K = 5 and 10 only, one seed")
    ap.add_argument("--noise", action="store_true",
                    help="only the ratio against the beads' photons (K = 10, seeds 0-2)")
    args = ap.parse_args()
    if args.noise:
        return noise_sweep()
    ks = [5, 10] if args.quick else [5, 10, 20]
    rows = []
    for n_beads in (24, 7):
        for k in ks:
            rows.append(row(k, n_beads, 0))
            print(f"  K={k}, {n_beads} beads: ratio {rows[-1]['ratio']:.2f}", flush=True)
    base = row(10, 24, 0)
    for n_psf, n_space in ((5, 5), (5, 10), (8, 16)):
        rows.append(row(10, 24, 0, n_psf, n_space, alone=base["alone"]))
    cols = [("K", "d"), ("beads", "d"), ("seed", "d"), ("photons", ".2f"), ("I", "d"), ("J", "d"),
            ("subspace", ".4f"), ("alone", ".4f"), ("ratio", ".2f"), ("seconds", ".1f")]
    print("\nSubspace against one image at a time (mean per-image PSF-field error)")
    print(table(rows, cols))


def noise_sweep():
    """The ratio against the beads' photons (x the simulator's default), K = 10."""
    rows = []
    for n_beads in (24, 7):
        for photons in (5.0, 1.0, 0.25):
            for seed in (0, 1, 2):
                rows.append(row(10, n_beads, seed, photons=photons))
                print(f"  {n_beads} beads, photons x{0.2 * photons:g}, seed {seed}: ratio "
                      f"{rows[-1]['ratio']:.2f}", flush=True)
    cols = [("K", "d"), ("beads", "d"), ("seed", "d"), ("photons", ".2f"), ("I", "d"),
            ("J", "d"), ("subspace", ".4f"), ("alone", ".4f"), ("ratio", ".2f")]
    print("\nSubspace against one image at a time, against the beads' photons")
    print(table(rows, cols))


if __name__ == "__main__":
    main()
