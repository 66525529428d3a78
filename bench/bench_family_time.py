"""Learning a family against one estimate per image, timed in the same run (issue 24).

    python bench/bench_family_time.py [--k 10] [--size 1024] [--beads 100] [--repeats 3]
        [--cache FILE]

``K`` images under the wide conditions of ``bench_family_oracle.py`` (bright beads,
defaults everywhere) are simulated once into ``--cache``; then ``estimate_family``
(the held-out choice on, the default) and ``K`` calls of ``estimate_operator`` are
timed in turn, ``--repeats`` times, interleaved so that a change of the machine's load
falls on both, after one untimed run of each. Issue 24: the family within 1.5x the
single estimates. To compare two versions of the code on the same images, run it with
each on ``PYTHONPATH`` (the first line printed names the package used).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from benchlib import table


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--beads", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cache", default="/tmp/psfspace-bench-family-time.npz")
    args = ap.parse_args()
    import napari_psfspace
    from napari_psfspace.core.family import estimate_family
    from napari_psfspace.core.model.estimate import estimate_operator

    key = (args.k, args.size, args.beads)
    images = None
    if os.path.exists(args.cache):
        with np.load(args.cache, allow_pickle=False) as got:
            if tuple(got["key"]) == key:
                images, r = list(got["images"]), int(got["r"])
    if images is None:
        from bench_family_oracle import WIDE
        from napari_psfspace.core.simulation.stacks import random_conditions, simulate_stack

        conds = random_conditions(args.k, [0, 1], WIDE)
        images, truths, _ = simulate_stack(args.k, (args.size, args.size), args.beads,
                                           seed=0, conditions=conds, amplitude=(2e4, 3e4))
        r = int(np.median([t.psf_radius for t in truths]))
        np.savez(args.cache, key=np.array(key), images=np.stack(images), r=r)
    print(napari_psfspace.__file__, flush=True)
    # warm-up: the whole family and one single estimate once, so that first calls' costs
    # (imports, caches) fall outside the timings (three images would not reach the
    # family's choice of dimensions)
    estimate_family(images, psf_radius=r)
    estimate_operator(images[0], psf_radius=r)
    rows = []
    for rep in range(args.repeats):
        t0 = time.perf_counter()
        estimate_family(images, psf_radius=r)
        family = time.perf_counter() - t0
        t0 = time.perf_counter()
        for im in images:
            estimate_operator(im, psf_radius=r)
        single = time.perf_counter() - t0
        rows.append({"repeat": rep, "family_s": family, "singles_s": single,
                     "ratio": family / single})
        print(rows[-1], flush=True)
    rows.append({"repeat": -1, "family_s": float(np.median([x["family_s"] for x in rows])),
                 "singles_s": float(np.median([x["singles_s"] for x in rows])),
                 "ratio": float(np.median([x["ratio"] for x in rows]))})
    print(table(rows, [("repeat", "d"), ("family_s", ".2f"), ("singles_s", ".2f"),
                       ("ratio", ".2f")]))


if __name__ == "__main__":
    main()
