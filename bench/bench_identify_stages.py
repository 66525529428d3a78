"""Where the identification's error enters: an oracle per stage, on chosen draws of the
learning curve (issue 63).

    python bench/bench_identify_stages.py [--generator ours|pyotf|psfmodels]
        [--case SEED IMAGE DRAW ...] [--beads 5] [--images 10] [--cache DIR] [--no-ideal]

Each case is one of ``bench_identify_curve``'s draws, drawn the same way (its seeds, its
default ``--beads`` and ``--draws``): ``P`` random beads of test image ``IMAGE`` of
``SEED``'s scene, draw ``DRAW``. Every figure is a PSF error over the field (aligned, 4 x 4
grid) over that of the image's own estimate from all its beads, as in the learning curve:

- ``default``: ``identify_operator`` from the clicked beads of the image;
- ``oracle``: the same, from the same beads of the image rendered without noise (the
  learning curve's oracle: each bead's patch as the extraction makes it);
- ``model_floor``: the family's model fitted to every bead of the image rendered without
  noise (each bead weighed by the clicked ones' noise), nothing kriged: how near the
  family's few numbers come to the image, exact data all over the field;
- ``space_floor``: every coefficient's map fitted to the same beads in the span of the
  family's spatial maps (its ``space``), each image's own freedom there: what the family's
  space allows, its few numbers aside;
- ``oracle_all``: the identification from every bead of the image rendered without
  noise, the family's miss kriged (the learning curve's oracle with all beads);
- ``ideal``: the true microscope, only its three conditions unknown, fitted to the same
  noisy patches (the simulator renders and the extraction cuts each candidate): what the
  five beads themselves determine. Its ``z`` beside the truth's (normalised conditions:
  focus, tilt in y, tilt in x).

So ``ideal`` is what the five beads allow, ``model_floor`` what the family's few numbers
allow (``space_floor`` what its maps allow), ``oracle`` what they make of exact data at
the five beads, and ``default`` adds the beads' noise.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np
from scipy.optimize import least_squares

from bench_identify_curve import BEADS as CURVE_BEADS
from bench_identify_curve import DRAWS as CURVE_DRAWS
from bench_identify_curve import clean_image, error, identify, picks_of
from benchlib import table
from identify_scenes import SPREADS, Cached, _truth_of, conditions, inner, make_scene
from napari_psfspace.core.common.spacing import partial_border
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.family.coordinates import bilinear
from napari_psfspace.core.family.curve import identify_any
from napari_psfspace.core.family.dimensions import family_model
from napari_psfspace.core.family.patches import image_patches
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.restore.identify import coefficients_on, field_operator
from napari_psfspace.core.simulation.aberrations import PRESETS, FieldAberrations
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.optics import RENDER_RADIUS_FACTOR
from napari_psfspace.core.simulation.render import render_beads

#: The cases by default: each generator's worst 5-bead draw inside the range in the
#: learning curve, and a typical one of the same scene.
CASES = {"ours": [(8, 2, 1), (8, 0, 0)], "pyotf": [(9, 1, 1), (9, 0, 0)],
         "psfmodels": [(0, 0, 0)]}


#: Starts of the true microscope's fit (the candidates of least cost among no tilt and
#: the training images' conditions), and its evaluations at most from each.
IDEAL_STARTS = 3
IDEAL_EVALUATIONS = 40


class TruePsfs:
    """The truth as an operator for :func:`grid_errors` (its PSFs exact everywhere)."""

    def __init__(self, truth, like):
        self.truth, self.shape, self.psf_size = truth, like.shape, like.psf_size

    def psf_at(self, y, x):
        return self.truth.psf_at(y, x, self.psf_size)


def beads_of(scene, seed, image, draw, beads):
    """The clicked beads of a case, drawn as ``bench_identify_curve`` draws them."""
    rng = np.random.default_rng([seed, 11])
    r = scene.psf_radius
    for t, (img, truth) in enumerate(zip(scene.tests, scene.test_truths, strict=True)):
        for p in CURVE_BEADS:
            picks = picks_of(truth, img.shape, r, p, CURVE_DRAWS, rng)
            if t == image and p == beads:
                return picks[draw][1]
    raise ValueError(f"no draw of {beads} beads of image {image} in seed {seed}")


def ideal_fit(image, truth, beads, r, z_starts, spread):
    """The true microscope's three conditions fitted to the beads' noisy patches by least
    squares (each bead weighed by its noise), from the :data:`IDEAL_STARTS` of
    ``z_starts`` that fit best; the fit of least cost."""
    base = FieldAberrations(PRESETS["moderate"])
    found = image_patches(image, r, positions=beads, border=partial_border(r)).patches
    weight = found.flux / found.noise

    def patches_at(z):
        t = _truth_of(conditions(z, spread)[0].aberrations(base), image.shape,
                      truth.optics, beads)
        img = np.zeros(image.shape)
        render_beads(img, beads, np.full(len(beads), 1e5), t.aberrations, truth.optics,
                     RENDER_RADIUS_FACTOR * t.psf_radius)
        return image_patches((img + 100.0).astype(np.float32), r, positions=beads,
                             border=partial_border(r)).patches.psf

    def residual(z):
        return ((found.psf - patches_at(z)) * weight[:, None, None]).ravel()

    costs = [float((residual(z0) ** 2).sum()) for z0 in z_starts]
    fits = [least_squares(residual, z_starts[i], diff_step=1e-3, max_nfev=IDEAL_EVALUATIONS)
            for i in np.argsort(costs)[:IDEAL_STARTS]]
    z = min(fits, key=lambda f: f.cost).x
    return z, _truth_of(conditions(z, spread)[0].aberrations(base), image.shape,
                        truth.optics, truth.positions)


def run_case(scene, fam, seed, image, draw, args):
    r = scene.psf_radius
    img, truth0 = scene.tests[image], scene.test_truths[image]
    truth = Cached(truth0)
    beads = beads_of(scene, seed, image, draw, args.beads)
    own_op = estimate_operator(img, psf_radius=r)
    own = error(own_op, truth)
    model = family_model(fam)
    sd_scale = float(fam.metadata["dimensions"].get("noise_factor", 1.0))

    def fitted(c, sd, centers):
        _, (field, _, _) = identify_any(model, c, sd, centers, spread=False, krige=False)
        return error(field_operator(fam, field, c), truth) / own

    found = image_patches(img, r, positions=beads, border=partial_border(r)).patches
    sd = float(np.median(found.noise / found.flux)) * sd_scale
    clean = clean_image(truth0, img.shape)
    every = image_patches(clean, r, positions=inner(truth0.positions, img.shape, r),
                          border=partial_border(r)).patches
    c_every = coefficients_on(every.psf, fam.basis)
    _, (field, _, _) = identify_any(model, c_every, np.full(len(c_every), sd),
                                    every.centers, spread=False, krige=False)
    space = fam.space.reshape(fam.n_space, -1)  # (J, G): the family's spatial maps
    on_beads = bilinear(fam.grid, every.centers) @ space.T
    space_field = space.T @ np.linalg.lstsq(on_beads, c_every, rcond=None)[0]
    row = {"seed": seed, "image": image, "draw": draw,
           "rows": f"{beads[:, 0].min():.0f}-{beads[:, 0].max():.0f}",
           "cols": f"{beads[:, 1].min():.0f}-{beads[:, 1].max():.0f}",
           "default": error(identify(img, fam, beads)[0], truth) / own,
           "oracle": error(identify(clean, fam, beads)[0], truth) / own,
           "model_floor": error(field_operator(fam, field, c_every), truth) / own,
           "space_floor": error(field_operator(fam, space_field, c_every), truth) / own,
           "oracle_all": error(identify(clean, fam, None)[0], truth) / own}
    if args.ideal:
        t0 = time.perf_counter()
        starts = [np.zeros(3), *scene.z_train]
        z, est = ideal_fit(img, truth0, beads, r, starts, SPREADS[args.spread])
        row["ideal"] = float(np.mean(grid_errors(TruePsfs(Cached(est), own_op), truth,
                                                 n=4))) / own
        row["z_true"] = np.round(scene.z_test[image], 2).tolist()
        row["z_ideal"] = np.round(z, 2).tolist()
        row["ideal_s"] = time.perf_counter() - t0
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--generator", default="ours", choices=["ours", "pyotf", "psfmodels"])
    ap.add_argument("--case", type=int, nargs=3, action="append",
                    metavar=("SEED", "IMAGE", "DRAW"))
    ap.add_argument("--beads", type=int, default=5)
    ap.add_argument("--spread", default="default", choices=sorted(SPREADS))
    ap.add_argument("--images", type=int, default=10,
                    help="training images each family is learnt from")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--no-ideal", dest="ideal", action="store_false")
    args = ap.parse_args()
    if args.beads not in CURVE_BEADS or args.beads == 0:
        ap.error(f"--beads must be one of the learning curve's {CURVE_BEADS[:-1]}, "
                 f"got {args.beads}")
    cases = args.case or CASES[args.generator]
    rows, fams = [], {}
    warnings.simplefilter("ignore")
    for seed, image, draw in cases:
        scene = make_scene(seed, generator=args.generator, spread=args.spread,
                           k=args.images, cache=args.cache)
        if seed not in fams:
            fams[seed] = estimate_family(scene.train, psf_radius=scene.psf_radius)
        row = run_case(scene, fams[seed], seed, image, draw, args)
        rows.append(row)
        print(f"seed {seed} image {image} draw {draw}: done", flush=True, file=sys.stderr)
    fmt = [("seed", "d"), ("image", "d"), ("draw", "d"), ("rows", "s"), ("cols", "s"),
           ("default", ".2f"), ("oracle", ".2f"), ("model_floor", ".2f"),
           ("space_floor", ".2f"), ("oracle_all", ".2f")]
    if args.ideal:
        fmt += [("ideal", ".2f"), ("z_true", "s"), ("z_ideal", "s"), ("ideal_s", ".0f")]
        for row in rows:
            row["z_true"], row["z_ideal"] = str(row["z_true"]), str(row["z_ideal"])
    print(f"Where the error enters ({args.generator}, {args.beads} beads, families of "
          f"{args.images} images; each figure the "
          "PSF error over the field over the image's own estimate's):")
    print(table(rows, fmt))

if __name__ == "__main__":
    main()
