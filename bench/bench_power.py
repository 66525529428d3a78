"""Power curves: how often diagnose names an effect the estimator is not told about.

    python bench/bench_power.py [--scenes 20] [--first 0] [--cases issue|eight|all]
                                [--strengths issue|sweep] [--generator ours|pyotf|psfmodels]
                                [--no-oracle] [--workers 2]

``--cases eight`` is issue 46's list: effect-free scenes (false alarms), column offsets,
saturation, vignetting, hot pixels, a defocus gradient, motion, companions and a
compressive response, each at its default strength.

Scenes are drawn by :func:`~napari_psfspace.core.simulation.scene_set.random_scene` in the
setting of issue 9's foreign-simulator cases (1024 x 1024, 150 beads, moderate aberrations, 100 nm
pixels, bead brightness spread sigma 0.25), everything else from the scene set (NA,
emission, background 1-500 photons, camera gain, offset, read noise, 8/12/16-bit), with
calibration-grade beads (median peak 300-30000 photons). Each scene gets one effect at
one strength, and is diagnosed with the true PSF radius and nothing else.

Per case and strength it prints the share of diagnosed scenes where

- ``named``: the right effect was added (motion: reported in the model's record;
  a defocus gradient, which the model must follow itself: a change of its settings,
  basis size or field smoothing, or no change needed because the plain model already
  follows it: field error against the truth within 25 % of the same scene without it);
- ``named_dropped``: named, and the held-out error dropped (for throughput: the held-out
  photometric error) by the acceptance rule's margin;
- ``other``: another effect about the data was added;
- ``visible``: scenes where the effect can be seen in principle (motion: the true
  smear's first spectral zero lies inside the optics' cutoff, and both flanks of that
  zero line stand clear of the noise inside the band where the beads' signal is seen,
  so that a zero there can be told from noise;
  vignetting: the radial trend's F-test on the beads' *true* amplitudes, their own
  brightness spread included, reaches the test's threshold; a compressive response and
  companions: the acceptance rule keeps the effect with its *true* parameters, tried
  whatever the tests say, so that some held-out error can show it at all; the other
  effects are counted visible), and ``named_of_visible`` the share named among them.

Scenes diagnose refuses (too few usable beads) are counted apart. With ``--field``:
``field_drop``, the median over the named scenes of ``1 - final / plain`` field error
(``grid_errors`` 6 x 6 against the truth; plain: the estimator without the diagnosis,
and for hot pixels without its own masking of them); ``room``, the median of
``1 - twin / plain``, the twin being the same scene without the effect estimated the
same way (the drop no correction can much exceed); and ``own_below``, of the named
effect's kept steps whose own test reads the correction, how many read it below its
threshold. ``floor_ratio`` is the median held-out error over its noise floor before any
effect: near 1 the scene's
noise hides any effect (invisible in principle at that signal).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from bench_motion import motion_of, visible
from benchlib import table
from napari_psfspace.core.diagnosis.analysis import THRESHOLDS
from napari_psfspace.core.diagnosis.effects import REGISTRY
from napari_psfspace.core.diagnosis.loop import diagnose
from napari_psfspace.core.diagnosis.statistics import radial_trend
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.scene_set import random_scene

SETTING = {"shape": (1024, 1024), "n_beads": 150, "aberrations": "moderate",
           "pixel_size": 0.1, "spread": 0.25, "peak_photons": (300.0, 3e4)}
MODEL_SETTINGS = ("basis_size", "field_smoothing")


def _drift(length, seed):
    angle = np.random.default_rng([seed, 7]).uniform(0, np.pi)
    return {"drift": (float(length * np.sin(angle)), float(length * np.cos(angle)))}


#: case -> (effect that must be named, strengths at issue 9's level, sweep, effects(s, seed))
CASES = {
    "none": ("-", [0], [0], lambda s, seed: {}),
    "vignetting": ("illumination", [0.4], [0.2, 0.4, 0.6],
                   lambda s, seed: {"illumination": s}),
    "defocus gradient": ("model", [0.15], [0.075, 0.15, 0.3],
                         lambda s, seed: {"defocus_gradient": s}),
    "compressive response": ("nonlinearity", [0.15], [0.075, 0.15, 0.3],
                             lambda s, seed: {"nonlinearity": s}),
    "companions 1-3 px": ("neighbours", [0.1], [0.05, 0.1, 0.2],
                          lambda s, seed: {"neighbours": {"fraction": s,
                                                          "distance_px": (1.0, 3.0),
                                                          "amplitude": (0.5, 1.0)}}),
    "motion": ("motion", [3.0], [3.0, 5.0, 8.0], _drift),
    "column offsets": ("fixed_pattern", [4.0], [2.0, 4.0, 8.0],
                       lambda s, seed: {"column_offsets": s}),
    "row offsets": ("fixed_pattern", [4.0], [2.0, 4.0, 8.0],
                    lambda s, seed: {"row_offsets": s}),
    # clipped at this fraction of the brightest pixel of the scene without it (the level
    # is set in run(), where the scene is known)
    "saturation": ("saturation", [0.6], [0.8, 0.6, 0.4], lambda s, seed: {}),
    "hot pixels": ("outlier_pixels", [1e-3], [1e-4, 1e-3],
                   lambda s, seed: {"hot_pixels": (s, (1.0, 5.0))}),
    "background structure": ("background_structure", [30.0], [10.0, 30.0, 100.0],
                             lambda s, seed: {"background_structure": s}),
    "bead size": ("bead_size", [(0.1, 0.3)], [(0.1, 0.2), (0.1, 0.3), (0.1, 0.5)],
                  lambda s, seed: {"bead_size": s}),
}


def _truth_trend_z(truth, shape) -> float:
    """The vignetting test's statistic on the true amplitudes."""
    return radial_trend(truth.positions, truth.amplitudes, shape,
                         THRESHOLDS["amplitude_field"])["z"]


def _oracle(image, truth, p, name) -> bool:
    """Would the acceptance rule keep the effect with its *true* parameters, tried
    whatever the tests say? (The truth's response for a compressive one; for companions,
    every bead the truth gave one fitted jointly with it at its true position.) Where it
    would not, no held-out error of these beads can show the effect: invisible in
    principle by the rule's own measure."""
    base = REGISTRY[name]

    class Oracle(base):
        name = ""  # set below: a named subclass would register itself

        def evidence(self, analysis):
            return 2.0  # as if its own test were significant: the 2 % drop applies

        def fit(self, ctx, analysis):
            if name == "nonlinearity":
                return {"c": float(truth.effects["nonlinearity"]),
                        "x_ref_adu": float(truth.effects["nonlinearity_reference"])
                        * float(p["gain"]), "offset_adu": float(p["offset"])}
            # each bead the truth gave a companion: fitted jointly with it at its true
            # position, no longer learnt from (still judged)
            owners = truth.positions[np.asarray(truth.effects["companion_of"], int)]
            comp = np.asarray(truth.effects["companion_positions"], float)
            d = np.hypot(*(ctx.beads.positions[:, None, :] - owners[None]).transpose(2, 0, 1))
            hit = np.flatnonzero(d.min(axis=1) <= 2.0)
            return {"beads": hit.tolist(), "companions": comp[d[hit].argmin(axis=1)].tolist(),
                    "stretched": [], "count": int(len(hit))}

    Oracle.name = name
    REGISTRY[name] = Oracle
    try:
        d = diagnose(image, psf_radius=truth.psf_radius, effects=[name], max_steps=1)
    except ValueError:
        return False
    finally:
        REGISTRY[name] = base
    return name in d.added


def _optics_type(generator: str):
    if generator in ("pyotf", "psfmodels"):
        from benchlib import optics_type

        return optics_type(generator)
    from napari_psfspace.core.simulation.optics import Optics

    return Optics


#: Names under which a case's effect counts as named (hot pixels: masked before the fit,
#: or by the loop's outlier effect).
ALSO_NAMED = {"outlier_pixels": ("hot_pixels",)}


def _own_below(steps, names) -> bool | None:
    """The named effect's kept step read its own test below its threshold afterwards
    (None where no kept step of these names has a test that reads the correction)."""
    reads = [s.statistic.get("significant_after") for s in steps
             if s.effect in names and s.accepted and s.statistic]
    reads = [r for r in reads if r is not None]
    return (not any(reads)) if reads else None


def run(job) -> dict:
    case, strength, seed, generator, oracle, field = job
    name, _, _, make = CASES[case]
    row = {"case": case, "strength": str(strength), "seed": seed}
    optics_type = _optics_type(generator)
    effects = make(strength, seed)
    if case == "saturation":  # a level the brightest beads of this scene pass
        clean, _, _ = random_scene(seed, optics_type=optics_type, **SETTING)
        effects = {"saturation": float(strength) * float(clean.max())}
    image, truth, p = random_scene(seed, effects=effects, optics_type=optics_type, **SETTING)
    t0 = time.perf_counter()
    try:
        d = diagnose(image, psf_radius=truth.psf_radius)
    except ValueError as err:
        return {**row, "refused": True, "note": str(err)[:80]}
    added = d.added
    present = ({"saturation"} if int((image >= p["full_scale"]).sum()) or case == "saturation"
               else set())
    others = [e for e in added if e not in MODEL_SETTINGS and e != name and e not in present
              and e not in ALSO_NAMED.get(name, ())]
    steps = {s.effect: s for s in d.steps if s.effect}
    if field and added:
        # the operator the estimator gives without the diagnosis, against the truth
        from napari_psfspace.core.beads.detect import detect_beads
        from napari_psfspace.core.common.progress import run_with_progress
        from napari_psfspace.core.model.estimate import iter_estimate

        beads = None
        if name == "outlier_pixels":  # the estimator masks spikes itself: here it must not
            beads = detect_beads(image, truth.psf_radius)
            beads.hot_pixels = np.zeros((0, 2), int)
        plain = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius,
                                                beads=beads)).operator
        row["truth_plain"] = float(np.mean(grid_errors(plain, truth, n=6)))
        # the room there is: the same scene without the effect, estimated the same way
        # (no correction can bring the field error much below it)
        twin, ttruth, _ = random_scene(seed, optics_type=optics_type, **SETTING)
        try:
            est = run_with_progress(iter_estimate(twin, psf_radius=ttruth.psf_radius)).operator
            row["truth_twin"] = float(np.mean(grid_errors(est, ttruth, n=6)))
        except ValueError:
            pass
        row["own_below"] = _own_below(d.steps, [name, *ALSO_NAMED.get(name, ())])
    row.update(refused=False, added=", ".join(added) or "-", other=bool(others),
               floor_ratio=d.error_before / max(d.noise_floor, 1e-12),
               truth_final=float(np.mean(grid_errors(d.operator, truth, n=6))),
               seconds=time.perf_counter() - t0)
    if name == "motion":
        rec = d.operator.metadata.get("motion") or {}
        row["named"] = bool(rec.get("detected"))
        row["dropped"] = row["named"]  # reported, not removed: nothing to drop
        # the smear's zero inside the optics' cutoff, and the test, probed at the true
        # smear, finds both flanks of its zero line clear of the noise inside the band
        # (else no zero can be told from noise there)
        dy, dx = truth.effects["drift"]
        angle = float(np.rad2deg(np.arctan2(dy, dx))) % 180.0
        try:
            m = motion_of(image, truth, (float(strength), angle))
            row["visible"] = visible(m, truth, float(strength))
        except ValueError:
            row["visible"] = False
    elif name == "illumination":
        row["named"] = name in added
        row["dropped"] = row["named"] and steps[name].accepted
        # what the beads' true brightness shows: the radial trend's F-test on the true
        # amplitudes (illumination and the beads' own spread, no measurement noise);
        # below the test's threshold no method sees the vignetting at that significance
        row["visible"] = _truth_trend_z(truth, image.shape) >= THRESHOLDS["amplitude_field"]
    elif name == "-":  # no effect: nothing about the data may be added
        row["named"] = not others
        row["dropped"] = row["named"]
    elif name == "model":
        changed = [e for e in added if e in MODEL_SETTINGS]
        clean, ctruth, _ = random_scene(seed, optics_type=optics_type, **SETTING)
        try:
            ref = diagnose(clean, psf_radius=ctruth.psf_radius)
            row["truth_clean"] = float(np.mean(grid_errors(ref.operator, ctruth, n=6)))
            follows = row["truth_final"] <= 1.25 * row["truth_clean"]
        except ValueError:  # the same scene without the gradient is refused
            follows = False
        row["named"] = bool(changed) or follows
        row["dropped"] = follows and (bool(changed) or not added)
    else:
        names = [name, *ALSO_NAMED.get(name, ())]
        row["named"] = any(n in added for n in names)
        row["dropped"] = row["named"]
        if name in ("nonlinearity", "neighbours") and oracle:
            row["visible"] = _oracle(image, truth, p, name)
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--first", type=int, default=0, help="first seed")
    ap.add_argument("--cases", default="issue",
                    help="'issue' (issue 9's five), 'eight' (issue 46's eight effects and "
                         "effect-free scenes), 'all', or comma-separated names")
    ap.add_argument("--no-oracle", action="store_true",
                    help="skip the oracles that count the compressive response's and the "
                         "companions' visible scenes (each a second diagnosis)")
    ap.add_argument("--field", action="store_true",
                    help="also the field error of the plain estimate (grid_errors, 6 x 6) "
                         "where something was added: the drop the kept steps bring")
    ap.add_argument("--strengths", choices=("issue", "sweep"), default="issue")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--verbose", action="store_true", help="one line per scene")
    ap.add_argument("--json", help="also write the per-scene rows to this file")
    ap.add_argument("--generator", choices=("ours", "pyotf", "psfmodels"), default="ours",
                    help="the optics code of the PSFs: the project's simulator, pyotf or "
                         "psfmodels (bench/independent.py; pip install -e '.[bench]')")
    args = ap.parse_args()
    eight = ["none", "column offsets", "saturation", "vignetting", "hot pixels",
             "defocus gradient", "motion", "companions 1-3 px", "compressive response"]
    issue = ["vignetting", "defocus gradient", "compressive response",
             "companions 1-3 px", "motion"]
    cases = (issue if args.cases == "issue" else eight if args.cases == "eight"
             else list(CASES) if args.cases == "all"
             else [c.strip() for c in args.cases.split(",")])
    jobs = [(c, s, seed, args.generator, not args.no_oracle, args.field) for c in cases
            for s in CASES[c][1 if args.strengths == "issue" else 2]
            for seed in range(args.first, args.first + args.scenes)]
    rows = []
    with ProcessPoolExecutor(args.workers) as pool:
        for i, r in enumerate(pool.map(run, jobs)):
            rows.append(r)
            print(f"[{i + 1}/{len(jobs)}] {r['case']} {r['strength']} seed {r['seed']}: "
                  f"{'refused' if r['refused'] else r['added']}", file=sys.stderr, flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1, default=float)
    if args.verbose:
        shown = [{**r, "named": str(r.get("named", "-")), "dropped": str(r.get("dropped", "-"))}
                 for r in rows]
        print(table(shown, [("case", "s"), ("strength", "s"), ("seed", "d"), ("added", "s"),
                            ("named", "s"), ("dropped", "s"), ("floor_ratio", ".2f"),
                            ("truth_final", ".4f"), ("truth_clean", ".4f"), ("truth_plain", ".4f"),
                            ("seconds", ".1f")]))
        print()
    out = []
    for c in cases:
        for s in CASES[c][1 if args.strengths == "issue" else 2]:
            rs = [r for r in rows if r["case"] == c and r["strength"] == str(s)]
            done = [r for r in rs if not r["refused"]]
            n = max(len(done), 1)
            out.append({"case": c, "effect": CASES[c][0], "strength": str(s),
                        "scenes": len(rs), "refused": len(rs) - len(done),
                        "named": sum(r["named"] for r in done) / n,
                        "named_dropped": sum(r["named"] and r["dropped"] for r in done) / n,
                        "other": sum(r["other"] for r in done) / n,
                        "visible": sum(r.get("visible", True) for r in done),
                        "named_of_visible": sum(r["named"] for r in done if r.get("visible", True))
                        / max(sum(r.get("visible", True) for r in done), 1),
                        "floor_ratio": float(np.median([r["floor_ratio"] for r in done]))
                        if done else None,
                        "truth_final": float(np.median([r["truth_final"] for r in done]))
                        if done else None})
            kept = [r for r in done if r["named"] and "truth_plain" in r]
            out[-1]["field_drop"] = (float(np.median([1 - r["truth_final"] / r["truth_plain"]
                                                      for r in kept])) if kept else None)
            twins = [r for r in kept if "truth_twin" in r]
            out[-1]["room"] = (float(np.median([1 - r["truth_twin"] / r["truth_plain"]
                                                for r in twins])) if twins else None)
            reads = [r["own_below"] for r in kept if r.get("own_below") is not None]
            out[-1]["own_below"] = f"{sum(reads)} of {len(reads)}" if reads else "-"
    print(table(out, [("case", "s"), ("effect", "s"), ("strength", "s"), ("scenes", "d"),
                      ("refused", "d"), ("named", ".2f"), ("named_dropped", ".2f"),
                      ("visible", "d"), ("named_of_visible", ".2f"),
                      ("other", ".2f"), ("floor_ratio", ".2f"), ("truth_final", ".4f"),
                      *([("field_drop", ".2f"), ("room", ".2f"), ("own_below", "s")]
                        if args.field else [])]))


if __name__ == "__main__":
    main()
