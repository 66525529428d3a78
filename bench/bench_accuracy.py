"""Accuracy of estimate_operator on the simulator: the issue's two headline cases, then
the error against bead count, noise level and basis size I.

    python bench/bench_accuracy.py [--quick]

Metric: rescaled relative l2 error min_c ||c est - true|| / ||true|| between the
estimated and true sum-normalised PSFs at an 8x8 grid of field positions (centres of an
8x8 tiling of the field), after the best sub-pixel translation ("aligned") or without
it; "edges" uses a grid reaching half a patch from the border; "SI" is the best single
shift-invariant PSF (mean of the true PSFs); ratio = aligned / SI.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchlib import add_generator_argument, optics_type, table
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.simulation import Optics, simulate_beads
from napari_psfspace.core.simulation.metrics import evaluate_against_truth

COLUMNS = [("case", "s"), ("seed", "d"), ("beads", "d"), ("peak_snr", ".0f"), ("I", "d"),
           ("aligned", ".4f"), ("max", ".4f"), ("unaligned", ".4f"), ("edges", ".4f"),
           ("SI", ".4f"), ("ratio", ".3f"), ("heldout", ".4f"), ("seconds", ".1f")]


#: the optics class of the scenes (``--generator``)
OPTICS = [Optics]


def run_case(case, shape, n_beads, preset, seed, n_psf=None, amplitude=(2e4, 6e4),
             **sim):
    sim.setdefault("optics", OPTICS[0]())
    image, truth = simulate_beads(shape, n_beads, aberrations=preset, seed=seed,
                                  amplitude=amplitude, **sim)
    t0 = time.perf_counter()
    est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius, n_psf=n_psf))
    dt = time.perf_counter() - t0
    r = evaluate_against_truth(est.operator, truth, 8)
    return {
        "case": case, "seed": seed, "beads": est.operator.metadata["n_beads_used"],
        "peak_snr": float(np.median(truth.peak_snr)), "I": est.operator.n_psf,
        "aligned": r["aligned"]["mean"], "max": r["aligned"]["max"],
        "unaligned": r["unaligned"]["mean"], "edges": r["edges"]["mean"],
        "SI": r["shift_invariant"]["mean"], "ratio": r["ratio"],
        "heldout": est.operator.metadata["heldout"]["residual_mean"], "seconds": dt,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed, fewer sweep points")
    ap.add_argument("--headline", action="store_true", help="only the headline cases")
    add_generator_argument(ap)
    args = ap.parse_args()
    OPTICS[0] = optics_type(args.generator)
    seeds = [0] if args.quick else [0, 1, 2]

    print("Headline cases (bounds: moderate mean <= 0.05, strong mean <= 0.12, "
          "ratio <= 0.333)")
    rows = [run_case("1024 moderate", (1024, 1024), 150, "moderate", s) for s in seeds]
    rows += [run_case("2048 strong", (2048, 2048), 400, "strong", s) for s in seeds]
    print(table(rows, COLUMNS), flush=True)
    if args.headline:
        return

    print("\nError against bead count (1024x1024, moderate, seed 0)")
    counts = [30, 60, 150] if args.quick else [20, 30, 60, 100, 150, 250]
    print(table([run_case(f"{n} beads", (1024, 1024), n, "moderate", 0) for n in counts],
                COLUMNS), flush=True)

    print("\nError against noise level (1024x1024, 150 beads, moderate; bead photons scaled)")
    levels = [0.1, 1.0] if args.quick else [0.05, 0.1, 0.3, 1.0, 3.0]
    print(table([run_case(f"x{f:g} photons", (1024, 1024), 150, "moderate", 0,
                          amplitude=(2e4 * f, 6e4 * f)) for f in levels], COLUMNS), flush=True)

    print("\nWide, strongly aberrated, low signal per pixel (issue 9): 2048x2048, 400 beads "
          "of 2e4 photons, background 100 photons, NA 1.3, 600 nm (target <= 0.08)")
    print(table([run_case(f"{1000 * px:.0f} nm pixels", (2048, 2048), 400, "strong", 0,
                          amplitude=2e4, background=100.0, optics=Optics(pixel_size=px))
                 for px in (0.1, 0.065)], COLUMNS), flush=True)

    print("\nError against basis size I (1024x1024, 150 beads, moderate, seed 0; "
          "auto = held-out choice)")
    sizes = [1, 3, 5, 9] if args.quick else [1, 2, 3, 4, 5, 6, 8, 10, 12]
    rows = [run_case(f"I={i}", (1024, 1024), 150, "moderate", 0, n_psf=i) for i in sizes]
    rows.append(run_case("I=rule", (1024, 1024), 150, "moderate", 0, n_psf="rule"))
    rows.append(run_case("I=auto", (1024, 1024), 150, "moderate", 0))
    print(table(rows, COLUMNS), flush=True)


if __name__ == "__main__":
    main()
