"""Identification from a few clicked beads over a wide range of conditions (issue 24).

    python bench/bench_identify_wide.py [--generator ours|pyotf|psfmodels] [--k 10]
        [--size 512] [--beads 36] [--tests 8] [--p 5] [--photons 1] [--seed 0]
        [--outside] [--border] [--min-separation PX]

A family is learnt from ``K`` images under wide hidden conditions (bench_family_oracle's
``WIDE``: focus through about +-1 depth of field at NA 1.3, tilts, spherical drift);
``--tests`` images come from other conditions inside the range learnt (``--outside``:
outside it, issue 45: drawn with 1.5x the spreads and kept where some parameter lies
beyond the range learnt). Each is identified from ``P`` beads well spread over the
field (farthest-point picks among the beads at least ``2 r`` from the border, ``r`` with
``--border``, at their true positions, as clicked with care) and from all its beads,
against ``estimate_operator`` on all its beads: PSF-field errors (aligned, 4 x 4 grid)
and their ratio. ``used`` is how many clicked beads were kept, ``spread`` the
identification's own confidence (the posterior spread of its PSFs, relative, mean over
the field; ``smax`` its largest), ``miss`` its error on the clicked beads beyond their
noise (``model_error``), ``warn`` the kind of warning (``miss``: the family does not
explain the clicked beads; ``bead``: one of them; ``spread``: they leave part of the
field undetermined). Issue 24: mean ratio <= 1.5, worst <= 2, and a warning on every
image worse than 2. Issue 45 (``--outside --border``): mean <= 1.5, worst <= 2.

``--oracle`` adds, per image, what the family's identification (its few dimensions) gives
from the truth's noise-free PSFs (windowed and normalised as patches are): ``clean5`` at
the ``P`` picked positions, ``clean_all`` at every bead's; ``span_all`` the paper's cone
of the ``Gamma_k`` from every bead, and ``best`` the family's best ``Gamma`` (least
squares on the truth at every node of the grid): each as a ratio to ``alone``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from bench_family_oracle import WIDE
from benchlib import optics_type, table
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.restore import identify_operator
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.stacks import random_conditions, simulate_stack, within


def spread_picks(positions: np.ndarray, shape, r: float, p: int, margin: float = 2.0
                 ) -> np.ndarray:
    """``p`` positions well spread over the field: farthest-point picks, starting from
    the one nearest the centre, among those at least ``margin r`` from the border."""
    h, w = shape
    m = margin * r
    inner = positions[(positions[:, 0] > m) & (positions[:, 0] < h - 1 - m)
                      & (positions[:, 1] > m) & (positions[:, 1] < w - 1 - m)]
    first = int(np.argmin(np.hypot(inner[:, 0] - h / 2, inner[:, 1] - w / 2)))
    picks = [first]
    d = np.hypot(*(inner - inner[first]).T)
    while len(picks) < min(p, len(inner)):
        nxt = int(np.argmax(d))
        picks.append(nxt)
        d = np.minimum(d, np.hypot(*(inner - inner[nxt]).T))
    return inner[picks]


def warn_kind(warning: str | None) -> str:
    """The kind of an identification's warning: ``miss`` (the clicked beads), ``bead``
    (one of them), ``spread`` (part of the field undetermined) or ``no``."""
    if not warning:
        return "no"
    if "clicked bead at" in warning:
        return "bead"
    return "spread" if "undetermined" in warning else "miss"


def clean_oracle(sub, truth, pick, r, alone) -> dict:
    """Identification from the truth's noise-free PSFs, and the family's best Gamma."""
    from napari_psfspace.core.beads.window import bump_window
    from napari_psfspace.core.family.result import space_at
    from napari_psfspace.core.restore import identify as idt

    size = sub.basis.shape[1]
    window = bump_window(size, float(r), 1.2 * float(r))

    def coef(points):
        psf = np.array([truth.psf_at(y, x, size) for y, x in points]) * window
        psf = (psf / psf.sum(axis=(1, 2), keepdims=True)).reshape(len(psf), -1)
        flat = sub.basis.reshape(sub.n_psf, -1)  # least squares, as identify_operator's
        return np.linalg.lstsq(flat.T, psf.T, rcond=None)[0].T

    def err(gamma):
        op = sub.operator_from(gamma, project=False)
        return float(np.mean(grid_errors(op, truth, n=4))) / alone

    from napari_psfspace.core.family.coordinates import identify_field
    from napari_psfspace.core.family.dimensions import family_model

    out = {}
    for name, points in (("clean5", pick), ("clean_all", truth.positions)):
        c = coef(points)
        field, _, _ = identify_field(family_model(sub), c, np.full(len(c), 1e-4),
                                     np.asarray(points, float), spread=False)
        out[name] = float(np.mean(grid_errors(idt.field_operator(sub, field, c), truth,
                                              n=4))) / alone
    at = space_at(sub.space, sub.grid, truth.positions)
    lam, g, _ = idt.solve_identification(coef(truth.positions),
                                         np.einsum("pj,kij->kpi", at, sub.gammas))
    out["span_all"] = err(np.tensordot(lam, sub.gammas, axes=1))
    gy, gx = sub.grid
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    best = np.linalg.lstsq(sub.space.reshape(sub.n_space, -1).T, coef(nodes), rcond=None)[0]
    out["best"] = err(best.T)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--generator", choices=("ours", "pyotf", "psfmodels"), default="ours")
    ap.add_argument("--outside", action="store_true",
                    help="test conditions outside the range learnt (issue 45): drawn with "
                         "1.5x the spreads and kept where not inside it")
    ap.add_argument("--min-separation", type=float, default=None,
                    help="least distance between beads, px (default 2.5 r, r of the "
                         "generator's PSF: wider for pyotf and psfmodels)")
    ap.add_argument("--border", action="store_true",
                    help="pick among every bead at least r from the edge (issue 45), "
                         "not 2r")
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--beads", type=int, default=36)
    ap.add_argument("--tests", type=int, default=8)
    ap.add_argument("--p", type=int, default=5)
    ap.add_argument("--photons", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--paper", action="store_true",
                    help="the paper's identification (the cone alone), for comparison")
    ap.add_argument("--oracle", action="store_true",
                    help="also identify from the truth's noise-free PSFs (see above)")
    args = ap.parse_args()
    optics = None
    if args.generator != "ours":
        optics = optics_type(args.generator)(na=1.3, wavelength=0.6, pixel_size=0.065)
    amp = {"amplitude": (2e4 * args.photons, 3e4 * args.photons)}
    if args.min_separation is not None:
        amp["min_separation"] = args.min_separation
    shape = (args.size, args.size)
    conds = random_conditions(args.k, [args.seed, 1], WIDE)
    images, truths, seen = simulate_stack(args.k, shape, args.beads, seed=args.seed,
                                          conditions=conds, optics=optics, **amp)
    r = int(np.median([t.psf_radius for t in truths]))
    t0 = time.perf_counter()
    sub = estimate_family(images, psf_radius=r)
    print(f"family: I = {sub.n_psf}, J = {sub.n_space}, {time.perf_counter() - t0:.1f} s",
          flush=True)
    wider = {k: 1.5 * v for k, v in WIDE.items()} if args.outside else WIDE
    draws = random_conditions(400, [args.seed, 2], wider)
    inside = within(draws, seen)
    unseen = [c for c, ok in zip(draws, inside, strict=True) if ok != args.outside]
    if len(unseen) < args.tests:
        print(f"only {len(unseen)} of 400 draws {'outside' if args.outside else 'inside'} "
              "the range learnt")
    new, new_truths, _ = simulate_stack(len(unseen[:args.tests]), shape, args.beads,
                                        seed=args.seed + 100, conditions=unseen[:args.tests],
                                        optics=optics, **amp)
    rows = []
    for k, (im, t) in enumerate(zip(new, new_truths, strict=True)):
        alone = float(np.mean(grid_errors(estimate_operator(im, psf_radius=r), t, n=4)))
        every = float(np.mean(grid_errors(identify_operator(im, sub, prior=not args.paper), t,
                                           n=4)))
        pick = spread_picks(t.positions, shape, r, args.p, 1.0 if args.border else 2.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            op = identify_operator(im, sub, beads=pick, prior=not args.paper)
        ident = op.metadata["identification"]
        err = float(np.mean(grid_errors(op, t, n=4)))
        rows.append({"gen": args.generator, "k": k, "focus": unseen[k].focus,
                     "used": int(ident["n_beads"]),
                     "alone": alone, "all": every, "picked": err, "ratio": err / alone,
                     "spread": float(ident.get("psf_spread") or np.nan),
                     "smax": float(ident.get("psf_spread_max") or np.nan),
                     "miss": float(ident["model_error"]),
                     "warn": warn_kind(ident.get("warning")),
                     **(clean_oracle(sub, t, pick, r, alone) if args.oracle else {})})
        print(rows[-1], flush=True)
    ratios = np.array([r_["ratio"] for r_ in rows])
    extra = [("clean5", ".2f"), ("clean_all", ".2f"), ("span_all", ".2f"),
             ("best", ".2f")] if args.oracle else []
    print(table(rows, [("gen", "s"), ("k", "d"), ("focus", ".3f"), ("used", "d"), ("alone", ".4f"),
                       ("all", ".4f"), ("picked", ".4f"), ("ratio", ".2f"),
                       ("spread", ".3f"), ("smax", ".3f"), ("miss", ".3f"), ("warn", "s"),
                       *extra]))
    worse = [r_["k"] for r_ in rows if r_["ratio"] > 2]
    missed = [r_["k"] for r_ in rows if r_["ratio"] > 2 and r_["warn"] == "no"]
    print(f"P = {args.p}: ratio mean {ratios.mean():.2f}, worst {ratios.max():.2f}; "
          f"images worse than 2x: {worse}, of which without a warning: {missed}")


if __name__ == "__main__":
    main()
