"""The deblur's stopping rule and its polish, on a family of scenes (issue 24, point 5).

    python bench/bench_deblur_tol.py [--tols 1e-4 5e-4] [--polish off on] [--data ../shared/data]

``deblur`` stops when the running minimum of its objective falls by less than ``tol``
(relatively) over 10 iterations; with ``polish`` FISTA stops at 1e-3 and coordinate
descent on the support takes it to ``tol`` (``core/restore/polish.py``). Each scene is
deblurred with each setting from the same operator; a setting is acceptable where no
scene's figure drops:

- ``sim s``: ``bench_deblur.py``'s scene of seed ``s`` (points on filaments, 512 x 512,
  the operator identified from 5 beads): F1 of the points found (best threshold,
  matched within 1.5 px);
- ``sample``: the panel's sample (768 x 768, 90 beads; ``estimate_operator`` on it):
  F1 of the true bead centres found;
- ``sp8 +o`` and ``astig +o``: the measured slice ``o`` slices from focus (family from
  the slices around focus without it, its operator identified from its own beads):
  the correlation of the output, refocused through the in-focus slice's own operator,
  with the in-focus slice (``bench_deblur_measured.py``).

Columns: FISTA iterations, the polish's sweeps, seconds (this machine, whatever else
runs on it), the figure, and on measured slices the median FWHM (px) of the deblurred
beads found isolated in the in-focus slice (how far each bead's cluster has
concentrated, which neither figure sees). About 15 min for two settings.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench_deblur import LOW, detect, scene
from bench_deblur_measured import corr, fwhm
from benchlib import table
from napari_psfspace._sample_data import simulated_beads
from napari_psfspace.core.beads.detect import detect_beads
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.restore import deblur, identify_operator
from napari_psfspace.core.simulation.stacks import random_conditions, simulate_stack, within
from napari_psfspace.io import best_focus_index, read_image

MEASURED = {
    # name: (file, PSF radius in px (None: 0.5 um), half-width of the family's slices)
    "sp8": ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", None, 6),
    "astig": ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", 10.0, 6),
}


def simulated(seeds):
    """(name, image, operator, figure(deblurred) -> float) for bench_deblur's scenes."""
    shape = (512, 512)
    images, truths, seen = simulate_stack(16, shape, 30, seed=100, **LOW)
    r = int(np.median([t.psf_radius for t in truths]))
    sub = estimate_family(images, psf_radius=r, holdout=None)
    draws = random_conditions(200, seed=7)
    unseen = [c for c, ok in zip(draws, within(draws, seen), strict=True) if ok]
    for seed in seeds:
        rng = np.random.default_rng(seed)
        _, (truth,), _ = simulate_stack(1, shape, 5, seed=200 + seed,
                                        conditions=[unseen[seed]])
        _, image, pts, beads = scene(truth, shape, rng, n_beads=5)
        op = identify_operator(image, sub, beads=beads + rng.normal(0, 0.5, beads.shape))

        def f1(res, pts=pts):
            recall, precision, _ = detect(res.sparse, pts)
            return 2 * recall * precision / max(recall + precision, 1e-12)
        yield f"sim {seed}", image, op, "F1", f1, None


def sample():
    (image, meta, _), (pts, _, _) = simulated_beads()[:2]
    op = estimate_operator(image, psf_radius=meta["metadata"]["psf_radius"], holdout=None)

    def f1(res):
        recall, precision, _ = detect(res.sparse, np.asarray(pts))
        return 2 * recall * precision / max(recall + precision, 1e-12)
    yield "sample", image, op, "F1", f1, None


def measured(data: Path, name: str, offsets):
    rel, r, half = MEASURED[name]
    path = data / rel
    n = len(__import__("tifffile").TiffFile(path).pages)
    stack = np.stack([read_image(path, index=z)[0] for z in range(n)])
    if r is None:
        r = 0.5 / read_image(path, index=0)[1].pixel_size
    f = best_focus_index(stack)
    focus = stack[f].astype(np.float32)
    op_focus = estimate_operator(stack[f], psf_radius=r, holdout=None)
    beads = detect_beads(stack[f], r)
    pos = beads.positions[beads.kept]
    for off in offsets:
        t = f + off
        train = [z for z in range(f - half, f + half + 1) if z != t]
        sub = estimate_family([stack[z] for z in train], psf_radius=r, holdout=None)
        op = identify_operator(stack[t].astype(np.float32), sub)

        def refocused(res):
            return corr(op_focus.apply(res.image), focus)
        yield f"{name} +{off}", stack[t].astype(np.float32), op, "refocused", refocused, pos


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tols", type=float, nargs="+", default=[1e-4])
    ap.add_argument("--polish", nargs="+", default=["off", "on"], choices=["off", "on"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--data", type=Path,
                    default=Path(__file__).resolve().parents[2] / "shared" / "data")
    args = ap.parse_args()
    import warnings
    warnings.simplefilter("ignore")  # identification warnings: reported by their benches
    scenes = [simulated(args.seeds), sample()]
    if args.data.is_dir():
        scenes += [measured(args.data, "sp8", (3, 8)), measured(args.data, "astig", (3,))]
    else:
        print(f"no data folder at {args.data}: measured scenes skipped")
    rows = []
    for gen in scenes:
        for name, image, op, what, figure, pos in gen:
            for tol in args.tols:
                for pol in args.polish:
                    t0 = time.perf_counter()
                    res = deblur(image, op, tol=tol, polish=pol == "on")
                    secs = time.perf_counter() - t0
                    width = (float(np.median(fwhm(res.image, pos))) if pos is not None
                             else float("nan"))
                    rows.append({"scene": name, "tol": f"{tol:g}", "polish": pol,
                                 "iterations": res.iterations,
                                 "sweeps": res.parameters["polish_sweeps"],
                                 "seconds": secs, "figure": what, "value": figure(res),
                                 "fwhm_px": width})
                    print(f"  {name} tol {tol:g} polish {pol}: {res.iterations} "
                          f"iterations + {rows[-1]['sweeps']} sweeps, {secs:.1f} s, {what} "
                          f"{rows[-1]['value']:.4f}, FWHM {width:.2f}", flush=True)
    print(table(rows, [("scene", "s"), ("tol", "s"), ("polish", "s"), ("iterations", "d"),
                       ("sweeps", "d"), ("seconds", ".1f"), ("figure", "s"),
                       ("value", ".4f"), ("fwhm_px", ".2f")]))


if __name__ == "__main__":
    main()
