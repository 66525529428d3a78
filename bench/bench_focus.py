"""Detection and best focus on every slice of through-focus bead stacks.

Every slice of a bead z-stack but one is out of focus: a disk or a ring many pixels
across. For each slice, as a user would run it: the PSF radius suggested from the slice,
then :func:`detect_beads` at that radius.

* Simulated focus series (:func:`simulate_focus_series`, the exact defocus phase), NA 0.8
  to 1.4, defocus -2 to +2 um in 0.25 um steps, widefield (rings far from focus), with
  and without the microscope's own field aberrations, and an astigmatic objective
  (elliptical rings); every bead isolated on every slice. Recall of the beads, splits
  (a bead found twice) and false detections (nowhere near a bead), per slice; the best
  focus against the true one.
* A dense slide of defocused elliptical rings (about 250 beads): the suggested radius,
  how many rings are found once, and how many are kept.
* Every stack in ``../shared/data``: beads found per slice (a count that doubles on a
  defocused slice shows), best focus against the slice of highest peak.

    python bench/bench_focus.py [--quick] [--no-measured] [--photons 0.1]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import tifffile
from scipy.spatial import cKDTree

from benchlib import table
from napari_psfspace.core.beads.detect import NoBeadsError, detect_beads
from napari_psfspace.core.beads.focus import best_focus_index
from napari_psfspace.core.beads.radius import suggest_psf_radius
from napari_psfspace.core.simulation import FieldAberrations, Optics
from napari_psfspace.core.simulation.focus import simulate_focus_series

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def score_slice(image, positions, true_r):
    """(suggested r, detections, recall, splits, false, recall of the usable beads) of
    one slice; usable: the bead's centre at least ``1.2 r + 2`` px (the estimate's border
    rule at the slice's true radius) from every edge of the image."""
    h, w = image.shape
    edge = np.minimum(np.minimum(positions[:, 0], h - 1 - positions[:, 0]),
                      np.minimum(positions[:, 1], w - 1 - positions[:, 1]))
    usable = edge >= 1.2 * true_r + 2
    try:
        r = suggest_psf_radius(image)
        beads = detect_beads(image, r)
    except NoBeadsError:
        return None, 0, 0.0, 0, 0, 0.0
    d, j = cKDTree(positions).query(beads.positions)
    hit = d <= max(3.0, 0.5 * true_r)
    found = np.unique(j[hit])
    inside = np.isin(np.flatnonzero(usable), found).mean() if usable.any() else 1.0
    return r, len(beads), len(found) / len(positions), int(hit.sum() - len(found)), \
        int((~hit).sum()), float(inside)


def simulated(quick: bool, photons: float = 1.0) -> list[dict]:
    z = np.arange(-2.0, 2.001, 0.5 if quick else 0.25)
    astig = FieldAberrations({6: (0.12,), 4: (0.0, 0.05), 8: (0.0, 0.04)})
    cases = [(na, ab, seed) for na in (0.8, 1.0, 1.2, 1.4)
             for ab, seed in (("moderate", 0), ("none", 1))]
    cases += [(1.2, "astigmatic", 2), (0.9, "astigmatic", 3)]
    if quick:
        cases = cases[::2]
    rows = []
    for na, ab, seed in cases:
        t = time.perf_counter()
        stack, series = simulate_focus_series(
            (768, 768), 18, z, optics=Optics(na=na, wavelength=0.6, pixel_size=0.1),
            aberrations=astig if ab == "astigmatic" else ab, seed=seed,
            amplitude=(5e4 * photons, 1.5e5 * photons))
        scores = [score_slice(stack[k], series.positions, series.psf_radius[k])
                  for k in range(len(z))]
        recall = np.array([s[2] for s in scores])
        n = len(series.positions)
        old = int(np.argmax(stack.reshape(len(stack), -1).astype(np.float32).std(axis=1)))
        rows.append({"NA": na, "aberrations": ab, "slices": len(z),
                     "min_recall": float(recall.min()),
                     "min_recall_usable": min(s[5] for s in scores),
                     "max_split_%": 100 * max(s[3] for s in scores) / n,
                     "max_false_%": 100 * max(s[4] for s in scores) / n,
                     "focus_true": series.focus_index, "focus": best_focus_index(stack),
                     "focus_std": old,
                     "r_suggested": f"{min(s[0] or 0 for s in scores):.0f}-"
                                    f"{max(s[0] or 0 for s in scores):.0f}",
                     "r_true": f"{series.psf_radius.min()}-{series.psf_radius.max()}",
                     "s": time.perf_counter() - t})
        print(rows[-1], flush=True)
    return rows


def dense_rings() -> dict:
    """About 250 defocused elliptical rings (astigmatism and 0.6 um of defocus)."""
    astig = FieldAberrations({6: (0.1,)})
    stack, series = simulate_focus_series(
        (1024, 1024), 250, [0.6], optics=Optics(na=1.3, wavelength=0.6, pixel_size=0.1),
        aberrations=astig, min_separation=40, seed=5)
    image = stack[0]
    r = suggest_psf_radius(image)
    beads = detect_beads(image, r)
    d, j = cKDTree(series.positions).query(beads.positions)
    hit = d <= max(3.0, 0.5 * series.psf_radius[0])
    found = np.unique(j[hit])
    return {"beads": len(series.positions), "r_true": int(series.psf_radius[0]),
            "r_suggested": r, "detections": len(beads),
            "found_once": int(len(found) - 0), "splits": int(hit.sum() - len(found)),
            "false": int((~hit).sum()), "kept": beads.counts()["kept"]}


def measured() -> list[dict]:
    rows = []
    for path in sorted(DATA.glob("*/*.tif")):
        stack = tifffile.imread(path)
        if stack.ndim != 3:
            continue
        counts = []
        for k in range(len(stack)):
            try:
                counts.append(len(detect_beads(stack[k], suggest_psf_radius(stack[k]))))
            except NoBeadsError:
                counts.append(0)
        counts = np.array(counts)
        # a jump: a slice with more than 1.5x (+2) the detections of both its neighbours
        # (the edge of detectability, where the beads' response crosses the threshold,
        # flickers); doubling: a defocused slice with more detections than 1.2x the
        # slice in focus (a ring found as several spots)
        jumps = [k for k in range(1, len(counts) - 1)
                 if counts[k] > 1.5 * max(counts[k - 1], counts[k + 1]) + 2]
        peak = int(np.argmax([np.percentile(s, 99.99) for s in stack]))
        focus = best_focus_index(stack)
        doubled = [k for k in range(len(counts)) if counts[k] > 1.2 * counts[focus] + 2]
        rows.append({"file": path.name, "slices": len(stack),
                     "counts": " ".join(str(c) for c in counts),
                     "jumps": ",".join(map(str, jumps)) or "-",
                     "doubled": ",".join(map(str, doubled)) or "-",
                     "in_focus": int(counts[focus]), "max_count": int(counts.max()),
                     "focus": focus, "peak_slice": peak,
                     "focus_std": int(np.argmax(
                         stack.reshape(len(stack), -1).astype(np.float32).std(axis=1)))})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-measured", action="store_true")
    ap.add_argument("--photons", type=float, default=1.0,
                    help="scale the beads' photons (default 1: 5e4-1.5e5 per bead and slice; "
                         "0.1 for faint beads)")
    args = ap.parse_args()
    rows = simulated(args.quick, args.photons)
    print(f"\nSimulated focus series (18 isolated beads, 768 x 768, 0.1 um pixels, "
          f"{5e4 * args.photons:.3g}-{1.5e5 * args.photons:.3g} photons per bead)")
    print(table(rows, [("NA", ".1f"), ("aberrations", "s"), ("slices", "d"),
                       ("min_recall", ".2f"), ("min_recall_usable", ".2f"),
                       ("max_split_%", ".0f"), ("max_false_%", ".0f"),
                       ("focus_true", "d"), ("focus", "d"), ("focus_std", "d"),
                       ("r_true", "s"), ("r_suggested", "s"), ("s", ".1f")]))
    d = dense_rings()
    print("\nDense slide of defocused elliptical rings")
    print(table([d], [(k, "") for k in d]))
    if not args.no_measured and DATA.is_dir():
        rows = measured()
        print("\nMeasured stacks: detections per slice (suggested radius per slice)")
        for r in rows:
            print(f"{r['file']} ({r['slices']} slices): {r['counts']}")
        print(table(rows, [("file", "s"), ("slices", "d"), ("in_focus", "d"),
                           ("max_count", "d"), ("doubled", "s"), ("jumps", "s"),
                           ("focus", "d"), ("peak_slice", "d"), ("focus_std", "d")]))


if __name__ == "__main__":
    main()
