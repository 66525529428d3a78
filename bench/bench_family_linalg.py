"""Where learning a family spends its time: the share of its dense linear algebra (SVD,
eigendecompositions, least squares, solves; every call in every thread), the part a GPU
could take (issue 48: "the family's heavy linear algebra, where it pays").

``K`` images simulated as in ``bench_family_time.py`` (bright beads, wide conditions) are
learnt with ``estimate_family`` at the defaults; each LAPACK entry point of NumPy and
SciPy is wrapped by a timer that adds its seconds and counts its calls and the size of
its largest matrix.

    python bench/bench_family_linalg.py [--k 10] [--size 1024] [--beads 100]
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np
import scipy.linalg

from benchlib import table

WRAPPED = [(np.linalg, "svd"), (np.linalg, "eigh"), (np.linalg, "lstsq"),
           (np.linalg, "solve"), (np.linalg, "inv"), (np.linalg, "qr"),
           (scipy.linalg, "svd"), (scipy.linalg, "eigh"), (scipy.linalg, "lstsq"),
           (scipy.linalg, "solve"), (scipy.linalg, "cho_factor"), (scipy.linalg, "qr")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--beads", type=int, default=100)
    args = ap.parse_args()
    from napari_psfspace.core.family import estimate_family
    from napari_psfspace.core.simulation.stacks import simulate_stack

    images, truths, _ = simulate_stack(args.k, (args.size, args.size), args.beads, seed=1)
    radius = int(np.median([t.psf_radius for t in truths]))
    stats: dict[str, list] = {}
    lock = threading.Lock()

    def wrap(mod, name):
        fn = getattr(mod, name)

        def timed(a, *rest, **kw):
            t0 = time.perf_counter()
            try:
                return fn(a, *rest, **kw)
            finally:
                dt = time.perf_counter() - t0
                with lock:
                    s = stats.setdefault(f"{mod.__name__}.{name}", [0, 0.0, 0])
                    s[0] += 1
                    s[1] += dt
                    s[2] = max(s[2], int(np.size(a)))
        setattr(mod, name, timed)
        return fn

    originals = [(mod, name, wrap(mod, name)) for mod, name in WRAPPED]
    t0 = time.perf_counter()
    try:
        estimate_family(images, psf_radius=radius)
    finally:
        total = time.perf_counter() - t0
        for mod, name, fn in originals:
            setattr(mod, name, fn)
    rows = [{"call": k, "calls": v[0], "seconds": v[1], "largest": v[2],
             "share": v[1] / total} for k, v in sorted(stats.items(), key=lambda kv: -kv[1][1])]
    rows.append({"call": "all linear algebra", "calls": sum(r["calls"] for r in rows),
                 "seconds": sum(r["seconds"] for r in rows),
                 "share": sum(r["share"] for r in rows)})
    print(f"estimate_family of {args.k} images of {args.size}^2, {args.beads} beads each: "
          f"{total:.1f} s (thread-seconds below: calls in parallel threads add up)")
    print(table(rows, [("call", "s"), ("calls", "d"), ("seconds", ".2f"),
                       ("largest", "d"), ("share", ".1%")]))


if __name__ == "__main__":
    main()
