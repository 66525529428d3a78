"""The clicked-bead check's threshold: single beads against bad ones (issue 63).

    python bench/bench_bead_check.py [--generators ours pyotf psfmodels] [--seeds 0 1]
        [--draws 20] [--cache DIR]

A family is learnt per seed (``identify_scenes``: 10 images of 1024 x 1024, 150 beads,
focus and tilts in y and x at the simulator's default spreads); on each of its 3 test
images inside the range, the check (``core/restore/bead_check``) scores 5 clicked beads
each left out: ``--draws`` random sets of single beads (the score of the bead the check
judges, the one whose absence leaves the others agreeing best: what a threshold must
pass), and sets of 4 single beads with one bad bead made in the
image: an unresolved pair (a copy of the bead 3 or 5 px beside it, the PSF's FWHM about
3.6 px), a saturated bead (its core clipped at 40 % of its peak), a bead under a bright
line (a ridge of 1.5 px sd and a third of its peak through it). Prints the quantiles of
the single sets' judged scores, of the bad beads' scores, and the share of each caught
(the bead judged, its score above the threshold) and of single sets with a bead left
out, at a few thresholds; the shape scores (a patch's energy outside the family's PSF
basis over its noise's) of the beads judged; and what the check's rule (both above their
thresholds) leaves out of each set.
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
from scipy import ndimage as ndi

from benchlib import table
from identify_scenes import inner, make_scene
from napari_psfspace.core.beads.window import bump_window
from napari_psfspace.core.common.spacing import partial_border
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.family.dimensions import family_model
from napari_psfspace.core.family.patches import image_patches
from napari_psfspace.core.restore.bead_check import (
    OUTLIER,
    SHAPE_OUTLIER,
    leave_one_out,
    shape_scores,
)
from napari_psfspace.core.restore.identify import coefficients_on

THRESHOLDS = (4.0, 6.0, 10.0, 20.0, 30.0, 50.0)


def scores_of(image, fam, model, r, picks):
    """The check's scores of beads clicked at ``picks`` (those kept by the patches):
    ``(scores, rest scores, shape scores)`` and their centres."""
    found = image_patches(image, r, positions=picks, border=partial_border(r))
    p = found.patches
    if p is None or len(p.centers) < 4:
        return None, None
    c = coefficients_on(p.psf, fam.basis)
    shapes = shape_scores(p.psf, c, fam.basis, p.noise / p.flux,
                          bump_window(p.size, p.r, p.r_ext))
    return (*leave_one_out(model, c, p.noise / p.flux, p.centers), shapes), p.centers


def isolated(positions, shape, r, far):
    """Beads at least ``far`` from every other and ``3 r + 1`` from the border (the
    region :func:`bad_image` changes lies inside)."""
    pts = inner(positions, shape, 3 * r + 1)
    d = np.hypot(*(pts[:, None] - positions[None]).transpose(2, 0, 1))
    d[d == 0] = np.inf
    return pts[d.min(axis=1) > far]


def bad_image(image, bead, kind, r, rng):
    """``image`` with the bead at ``bead`` made bad, and where to click it."""
    img = image.astype(np.float64).copy()
    y, x = np.round(bead).astype(int)
    h = int(3 * r)
    sl = (slice(y - h, y + h + 1), slice(x - h, x + h + 1))
    piece = img[sl] - np.median(img[sl])
    if kind.startswith("pair"):
        s = float(kind[4:])
        angle = rng.uniform(0, np.pi)
        shift = (s * np.sin(angle), s * np.cos(angle))
        img[sl] += ndi.shift(piece, shift, order=3)
        return img, np.asarray(bead) + 0.5 * np.array(shift)
    if kind == "saturated":
        bg = np.median(img[sl])
        core = img[y - r:y + r + 1, x - r:x + r + 1]
        level = bg + 0.4 * (core.max() - bg)
        img[y - r:y + r + 1, x - r:x + r + 1] = np.minimum(core, level)
        return img, np.asarray(bead, float)
    if kind == "line":
        bg = np.median(img[sl])
        peak = img[y - 2:y + 3, x - 2:x + 3].max() - bg
        yy, xx = np.mgrid[sl[0], sl[1]]
        angle = rng.uniform(0, np.pi)
        dist = (yy - bead[0]) * np.cos(angle) - (xx - bead[1]) * np.sin(angle)
        img[sl] += peak / 3 * np.exp(-0.5 * (dist / 1.5) ** 2)
        return img, np.asarray(bead, float)
    raise ValueError(kind)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generators", nargs="+", default=["ours"],
                    choices=("ours", "pyotf", "psfmodels"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--bad", type=int, default=4, help="bad beads of each kind per image")
    ap.add_argument("--cache", default=None)
    args = ap.parse_args()
    kinds = ("pair3", "pair5", "saturated", "line")
    rows = []
    for gen in args.generators:
        single, bad = [], {k: [] for k in kinds}
        for seed in args.seeds:
            sc = make_scene(seed, generator=gen, n_inside=3, n_beyond=0, cache=args.cache)
            r = sc.psf_radius
            fam = estimate_family(sc.train, psf_radius=r)
            model = family_model(fam)
            rng = np.random.default_rng([seed, 5])
            for image, truth in zip(sc.tests, sc.test_truths, strict=True):
                pts = inner(truth.positions, image.shape, r)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    for _ in range(args.draws):
                        s, _ = scores_of(image, fam, model, r,
                                         pts[rng.choice(len(pts), 5, replace=False)])
                        if s is not None and len(s[0]) == 5:
                            j = int(np.argmin(s[1]))
                            single.append((float(s[0][j]), float(s[2][j])))
                    alone = isolated(truth.positions, image.shape, r, 4 * r)
                    for kind in kinds:
                        for b in alone[rng.choice(len(alone), min(args.bad, len(alone)),
                                                  replace=False)]:
                            img, click = bad_image(image, b, kind, r, rng)
                            others = pts[np.hypot(*(pts - b).T) > 4 * r]
                            four = others[rng.choice(len(others), 4, replace=False)]
                            s, cen = scores_of(img, fam, model, r, np.vstack([four, click]))
                            if s is None or len(s[0]) < 5:
                                continue
                            j = int(np.argmin(np.hypot(*(cen - click).T)))
                            chosen = int(np.argmin(s[1]))
                            bad[kind].append((float(s[0][j]), bool(j == chosen),
                                              float(s[2][j])))
            print(f"{gen} seed {seed}: {len(single)} single sets", flush=True)
        sv = np.array([a for a, _ in single])
        sh = np.array([b for _, b in single])
        q = np.quantile(sv, [0.5, 0.9, 0.95, 0.99]) if len(sv) else [np.nan] * 4
        rows.append({"gen": gen, "set": "single x5", "n": len(sv), "q50": q[0],
                     "q90": q[1], "q95": q[2], "q99": q[3], "max": float(sv.max()),
                     "shape_q95": float(np.quantile(sh, 0.95)), "shape_max": float(sh.max()),
                     **{f"at{t:g}": np.mean(sv > t) for t in THRESHOLDS},
                     "rule": float(np.mean((sv > OUTLIER) & (sh > SHAPE_OUTLIER)))})
        for kind in kinds:
            v = np.array([a for a, _, _ in bad[kind]])
            top = np.array([t for _, t, _ in bad[kind]])
            shp = np.array([b for _, _, b in bad[kind]])
            if not len(v):
                continue
            qq = np.quantile(v, [0.5, 0.9, 0.95, 0.99])
            rows.append({"gen": gen, "set": kind, "n": len(v), "q50": qq[0], "q90": qq[1],
                         "q95": qq[2], "q99": qq[3], "max": float(v.max()),
                         "min": float(v.min()), "shape_min": float(shp.min()),
                         **{f"at{t:g}": float(np.mean(top & (v > t))) for t in THRESHOLDS},
                         "rule": float(np.mean(top & (v > OUTLIER) & (shp > SHAPE_OUTLIER)))})
    cols = [("gen", "s"), ("set", "s"), ("n", "d"), ("min", ".1f"), ("q50", ".1f"),
            ("q90", ".1f"), ("q95", ".1f"), ("q99", ".1f"), ("max", ".1f")]
    cols += [(f"at{t:g}", ".2f") for t in THRESHOLDS]
    cols += [("shape_q95", ".2f"), ("shape_max", ".2f"), ("shape_min", ".2f"),
             ("rule", ".2f")]
    print(f"\nScores of 5 clicked beads each left out; at T: single sets whose judged "
          "bead scores above T (left out on the score alone), bad beads caught (judged, "
          f"above T); shape: the judged single beads' shape scores (95th percentile, "
          f"largest) and the bad beads' least; rule: the check's (score above {OUTLIER:g} "
          f"and shape above {SHAPE_OUTLIER:g}): single sets with a bead left out, bad beads "
          "left out")
    print(table(rows, cols))


if __name__ == "__main__":
    main()
