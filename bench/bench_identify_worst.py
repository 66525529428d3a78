"""Whether five clicked beads can pin an image's operator down, and what the one more
bead the identification names does (issue 63's worst draws).

    python bench/bench_identify_worst.py [--generator ours|pyotf|psfmodels]
        [--seeds 0 1 ...] [--cache DIR] [--posterior 24] [--images 10]

The scenes, the random 5-bead draws and the own estimates of ``bench_identify_curve``
(the same seeds give the same draws): inside the range of conditions learnt, each draw's
identified operator's PSF-field error over the image's own estimate's (``default``),
whether the identification warned (``warned``), and the same with one more bead, the
image's bead nearest the place the identification names (``more_beads_at``: ``sixth``).

For the draws above 2 (and the worst draw, whatever it is), on a family along a curve
(:mod:`napari_psfspace.core.family.curve`): whether the five beads could tell the
identified point of the curve (``eta``, an image's condition at its centre and its
slopes) from the image's own point, the one identified from all of its beads without
noise:

- ``obj_found``, ``obj_own``: the identification's objective (the five beads' whitened
  residuals squared, plus the prior's ``|eta|^2``) of the five beads without noise, at
  the point identified from them (the oracle's) and at the image's own; ``res_found``,
  ``res_own``: its beads' part alone; ``gap``: ``obj_own - obj_found``. A gap under 1
  is within one standard deviation of the posterior: the beads cannot tell the two
  points apart. A residual lower at the identified point means the curve fits those five
  noise-free beads better there than at the image's own point: no fit to them prefers
  the right one.
- ``at_own``: the error at the image's own point, the miss kriged from the five beads;
- ``post_10``, ``post_50``, ``post_90``: the error's quantiles over points drawn from the
  identification's posterior (Laplace, ``--posterior`` draws): the range the five beads
  allow.
"""

from __future__ import annotations

import argparse
import warnings
from contextlib import contextmanager

import numpy as np

from bench_identify_curve import BEADS, DRAWS, clean_image, error, identify, picks_of
from benchlib import table
from identify_scenes import Cached, inner, make_scene
from napari_psfspace.core.family import curve as curve_module
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.family.coordinates import bilinear, whitener
from napari_psfspace.core.family.curve import Curve
from napari_psfspace.core.model.estimate import estimate_operator

AMPLITUDES = (0.5, 2.0)


@contextmanager
def recorded_fits(start=None, steps=None):
    """Record each :meth:`Curve.fit` (its curve, beads and result); ``start``: fit from
    it alone; ``steps``: at most that many Gauss-Newton steps (0: keep ``start``)."""
    calls: list[dict] = []
    fit, old_steps = Curve.fit, curve_module.FIT_STEPS

    def wrapped(self, c, sd, centers, **kw):
        if start is not None:
            kw["start"] = start
        model, found = fit(self, c, sd, centers, **kw)
        calls.append({"curve": self, "c": np.asarray(c), "sd": np.asarray(sd),
                      "centers": np.asarray(centers), "eta": found.z.copy(),
                      "cov": found.cov.copy()})
        return model, found

    Curve.fit = wrapped
    if steps is not None:
        curve_module.FIT_STEPS = steps
    try:
        yield calls
    finally:
        Curve.fit, curve_module.FIT_STEPS = fit, old_steps


def objective(curve: Curve, c, sd, centers, eta) -> tuple[float, float]:
    """The identification's objective at ``eta`` (its beads' part, and the whole): each
    bead's residual about the curve, whitened as :meth:`Curve.fit` does, its amplitude
    the best within the range, plus ``|eta|^2``."""
    white = whitener(curve.frame.gram)
    scale = curve.bead_scales(sd, centers)
    cv = (np.asarray(c, np.float64) @ white.T) * scale[:, None]
    fw = (bilinear(curve.frame.grid, centers) @ curve.field(eta) @ white.T) * scale[:, None]
    g = np.clip((fw * cv).sum(axis=1) / np.maximum((fw * fw).sum(axis=1), 1e-300),
                *AMPLITUDES)
    res = float(((cv - g[:, None] * fw) ** 2).sum())
    return res, res + float(np.dot(eta, eta))


def nearest(points: np.ndarray, at) -> np.ndarray:
    at = np.asarray(at, np.float64).reshape(-1, 2)[0]
    return points[int(np.argmin(((points - at) ** 2).sum(axis=1)))]


def run_seed(seed, args, rows, fams):
    sc = make_scene(seed, generator=args.generator, k=args.images, cache=args.cache)
    r = sc.psf_radius
    fam = estimate_family(sc.train, psf_radius=r)
    fams[seed] = (sc, fam)
    rng = np.random.default_rng([seed, 11])  # bench_identify_curve's draws
    for t, (image, truth0, beyond) in enumerate(zip(sc.tests, sc.test_truths, sc.beyond,
                                                    strict=True)):
        picks = [(p, m, b) for p in BEADS
                 for m, b in picks_of(truth0, image.shape, r, p, DRAWS, rng)]
        if beyond:
            continue
        truth = Cached(truth0)
        own = error(estimate_operator(image, psf_radius=r), truth)
        pts = inner(truth0.positions, image.shape, r)
        draw = 0
        for p, mode, beads in picks:
            if p != 5 or mode != "random":
                continue
            op, _ = identify(image, fam, beads)
            info = op.metadata["identification"]
            six = np.vstack([beads, nearest(pts, info["more_beads_at"])])
            op6, _ = identify(image, fam, six)
            rows.append({"seed": seed, "image": t, "draw": draw, "own": own,
                         "default": error(op, truth) / own, "warned": bool(info["warning"]),
                         "sixth": error(op6, truth) / own, "beads": beads})
            draw += 1
    print(f"seed {seed}: " + ", ".join(f"{q['default']:.2f}/{q['sixth']:.2f}"
                                       for q in rows if q["seed"] == seed), flush=True)


def identifiability(q, fams, n_draws):
    """The worst draw's row of the second table (see the module's notes)."""
    sc, fam = fams[q["seed"]]
    image, truth0 = sc.tests[q["image"]], sc.test_truths[q["image"]]
    truth, clean, own = Cached(truth0), clean_image(truth0, image.shape), q["own"]
    out = {k: q[k] for k in ("seed", "image", "draw", "default", "sixth")}
    with recorded_fits() as calls:
        identify(clean, fam, inner(truth0.positions, image.shape, sc.psf_radius))
    if not calls:
        return {**out, "kind": "lines"}
    eta_own = max(calls, key=lambda k: len(k["centers"]))["eta"]
    with recorded_fits() as calls:
        oracle, _ = identify(clean, fam, q["beads"])
    five = calls[0]
    args = (five["curve"], five["c"], five["sd"], five["centers"])
    (res_found, obj_found), (res_own, obj_own) = (objective(*args, five["eta"]),
                                                 objective(*args, eta_own))
    with recorded_fits() as calls:
        identify(image, fam, q["beads"])
    eta, cov = calls[0]["eta"], calls[0]["cov"]
    with recorded_fits(start=eta_own, steps=0):
        at_own, _ = identify(image, fam, q["beads"])
    rs = np.random.default_rng([q["seed"], q["image"], q["draw"]])
    factor = np.linalg.cholesky(cov)
    post = []
    for _ in range(n_draws):
        with recorded_fits(start=eta + factor @ rs.standard_normal(3), steps=0):
            post.append(error(identify(image, fam, q["beads"])[0], truth) / own)
    return {**out, "kind": "curve", "oracle": error(oracle, truth) / own,
            "obj_found": obj_found, "obj_own": obj_own, "gap": obj_own - obj_found,
            "res_found": res_found,
            "res_own": res_own, "at_own": error(at_own, truth) / own,
            **dict(zip(("post_10", "post_50", "post_90"),
                       np.quantile(post, [0.1, 0.5, 0.9]), strict=True))}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generator", choices=("ours", "pyotf", "psfmodels"), default="ours")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    ap.add_argument("--cache", default=None, help="a folder keeping the rendered scenes")
    ap.add_argument("--posterior", type=int, default=24,
                    help="points drawn from the posterior of each worst draw")
    ap.add_argument("--images", type=int, default=10,
                    help="training images each family is learnt from")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    rows: list[dict] = []
    fams: dict = {}
    for seed in args.seeds:
        run_seed(seed, args, rows, fams)
    d, s = np.array([q["default"] for q in rows]), np.array([q["sixth"] for q in rows])
    w = np.array([q["warned"] for q in rows])
    summ = [{"draws": len(rows), "default_mean": d.mean(), "default_worst": d.max(),
             "above_2": int((d > 2).sum()), "warned": float(w.mean()),
             "sixth_mean": s.mean(), "sixth_worst": s.max(), "sixth_above_2": int((s > 2).sum()),
             "warned_worst": float(np.max(d[w])) if w.any() else None,
             "quiet_worst": float(np.max(d[~w])) if (~w).any() else None}]
    print(f"\nInside the range, 5 random beads ({args.generator}, {len(args.seeds)} seeds, "
          f"families of {args.images} images): "
          "the identified operator's PSF-field error / the image's own estimate's; with "
          "one more bead where the identification names (sixth); the worst among the draws "
          "it warned on and among those it did not")
    print(table(summ, [("draws", "d"), ("default_mean", ".2f"), ("default_worst", ".2f"),
                       ("above_2", "d"), ("warned", ".2f"), ("warned_worst", ".2f"),
                       ("quiet_worst", ".2f"), ("sixth_mean", ".2f"), ("sixth_worst", ".2f"),
                       ("sixth_above_2", "d")]))
    worst = [q for q in rows if q["default"] > 2] or [max(rows, key=lambda q: q["default"])]
    found = [identifiability(q, fams, args.posterior) for q in worst]
    print("\nThe draws above 2 (or the worst): the five beads' objective without noise at the "
          "identified point and at the image's own (a difference under 1: within one "
          "standard deviation); the error there; over the posterior's points")
    print(table(found, [("seed", "d"), ("image", "d"), ("draw", "d"), ("kind", "s"),
                        ("default", ".2f"), ("oracle", ".2f"), ("sixth", ".2f"),
                        ("obj_found", ".2f"), ("obj_own", ".2f"), ("gap", ".2f"),
                        ("res_found", ".2f"),
                        ("res_own", ".2f"), ("at_own", ".2f"), ("post_10", ".2f"),
                        ("post_50", ".2f"), ("post_90", ".2f")]))


if __name__ == "__main__":
    main()
