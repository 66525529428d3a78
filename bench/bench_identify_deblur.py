"""BSS with the operator identified from 5 beads against the image's own full estimate
(issue 63).

    python bench/bench_identify_deblur.py [--seeds 0 1 2] [--cache DIR]
        [--generator ours|pyotf|psfmodels] [--max-iter 500]

Per seed (``identify_scenes``: a family learnt from 10 images of 1024 x 1024, 150 beads,
focus and tilts in y and x), each test condition inside the range learnt gives two
images: its bead image (150 beads: the calibration a microscopist would take, whose own
full estimate ``estimate_operator`` is the baseline) and a sample under the same
condition (``bench_deblur.scene``: points on filaments, 5 isolated beads, a smooth
background, blurred by the truth's operator, Poisson and read noise). The sample is
deblurred (``deblur``, its defaults) with:

- ``bss``: the operator identified from its 5 isolated beads (clicked within 0.5 px);
- ``own``: the bead image's own full estimate;
- ``oracle``: the true operator.

F1 of the points found within 1.5 px (``bench_deblur.detect``: each method at the
threshold of its best F1). Issue 63: ``bss`` keeps F1 within 0.03 of ``own``.
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np

from bench_deblur import detect, scene, true_operator
from benchlib import table
from identify_scenes import make_scene
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.restore import deblur, identify_operator


def f1(recall: float, precision: float) -> float:
    return 2 * recall * precision / max(recall + precision, 1e-12)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generator", choices=("ours", "pyotf", "psfmodels"), default="ours")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--max-iter", type=int, default=500)
    ap.add_argument("--cache", default=None)
    args = ap.parse_args()
    rows = []
    for seed in args.seeds:
        sc = make_scene(seed, generator=args.generator, cache=args.cache)
        r = sc.psf_radius
        fam = estimate_family(sc.train, psf_radius=r)
        for t, (beads_image, truth) in enumerate(zip(sc.tests, sc.test_truths, strict=True)):
            if sc.beyond[t]:
                continue
            rng = np.random.default_rng([seed, t, 3])
            _, sample, pts, isolated = scene(truth, beads_image.shape, rng, n_beads=5)
            clicked = isolated + rng.normal(0, 0.5, isolated.shape)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ops = {"bss": identify_operator(sample, fam, beads=clicked),
                       "own": estimate_operator(beads_image, psf_radius=r),
                       "oracle": true_operator(truth, beads_image.shape)}
            got = {}
            for name, op in ops.items():
                res = deblur(sample, op, max_iter=args.max_iter)
                recall, precision, err = detect(res.sparse, pts)
                got[name] = f1(recall, precision)
                rows.append({"seed": seed, "image": t, "method": name, "points": len(pts),
                             "recall": recall, "precision": precision, "f1": got[name],
                             "position_px": err})
            print(f"seed {seed} image {t}: " + ", ".join(f"{k} {v:.3f}" for k, v in got.items()),
                  flush=True)
    print("\nPoints found within 1.5 px after a deblur of the sample (1024 x 1024)")
    print(table(rows, [("seed", "d"), ("image", "d"), ("method", "s"), ("points", "d"),
                       ("recall", ".3f"), ("precision", ".3f"), ("f1", ".3f"),
                       ("position_px", ".2f")]))
    f = {m: np.array([q["f1"] for q in rows if q["method"] == m]) for m in ("bss", "own",
                                                                            "oracle")}
    diff = f["own"] - f["bss"]
    print(f"\nF1: bss {f['bss'].mean():.3f}, own {f['own'].mean():.3f}, oracle "
          f"{f['oracle'].mean():.3f}; own - bss: mean {diff.mean():.3f}, largest "
          f"{diff.max():.3f} (within 0.03 on every image: {bool(diff.max() <= 0.03)})")


if __name__ == "__main__":
    main()
