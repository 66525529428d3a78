"""Is the suggested PSF radius good enough? A sweep of the radius on every set.

:func:`suggest_psf_radius` (what the Beads step and the command line use when the user
gives no radius) is compared with a sweep of radii, factors ``FACTORS`` of the spots'
*visible* radius (``suggest_psf_radius(image, wings=1.0)``, what it suggested before),
on two kinds of sets:

* **simulated scenes** (the panel's sample and a family: the project's optics and pyotf,
  aberration-free to strong, bright and faint, dense and sparse): each radius's model,
  learnt from the beads a user gets at that radius, against the true PSFs on a 6 x 6
  grid, over the whole rendered PSF (``3 x`` the true 90 %-energy radius; the model is
  zero beyond its own patch): the field error of ``bench_accuracy``;
* **measured slices** (every ``--step``-th slice of the stacks in ``../shared/data``,
  and the star field): the project's one figure, the held-out error
  (:mod:`napari_psfspace.core.diagnosis.metric`), made comparable across radii. A model's
  held-out error is measured over its own patches, which grow with the radius: a small
  radius would be judged on its core only and never pay for the halo it cuts off. Here
  every radius is judged on the same beads in the same window: the beads kept at the
  sweep's largest radius (the largest that keeps enough of them isolated), in 5 folds;
  each radius learns from the beads a user gets at that radius, less the fold's, and the
  fold's beads are fitted (amplitude and background) within the largest radius, the model
  being zero beyond its own patch. ``error`` is the mean over those beads of the
  residual energy over one signal energy per bead, the same for every radius (the median
  over the radii of each model's fitted ``||A m||^2``); ``floor`` what noise alone
  leaves, on the same scale; ``own_error`` the one metric's figure, each model's residual
  over its own fitted signal, which a wider, flatter PSF makes larger where the residual
  is only noise (so it cannot rank radii there).

A set passes when the suggestion's error is within 1.2x of the sweep's best. On measured
slices the summary also gives the ratio's 5-95 % range over bootstrap resamples of the
judged beads (paired), and the noise floor over the error at the suggestion (above 1:
the noise in the judging window outweighs what the model misses). Prints one
table per set and a summary, and writes every row to ``bench/out/radius_sweep.jsonl``.

    python bench/bench_radius_sweep.py [--sets ours pyotf sp8 astig star] [--step 6]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import tifffile

from benchlib import optics_type, table
from napari_psfspace.core.beads.detect import HELDOUT, KEPT
from napari_psfspace.core.beads.radius import suggest_psf_radius
from napari_psfspace.core.beads.spikes import spike_mask
from napari_psfspace.core.common.errors import PsfSpaceError
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.diagnosis.crossfit import assign_folds
from napari_psfspace.core.diagnosis.loop import noise_model_with_source, prepare_beads
from napari_psfspace.core.diagnosis.residuals import BeadResiduals, fit_beads
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.simulation import simulate_beads
from napari_psfspace.core.simulation.metrics import grid_positions, psf_error
from napari_psfspace.core.simulation.optics import RENDER_RADIUS_FACTOR

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
OUT = Path(__file__).resolve().parent / "out"
FACTORS = (0.75, 1.0, 1.25, 1.5, 1.75, 2.0, 2.5)
TOLERANCE = 1.2
FOLDS = 5
#: Fewest beads isolated at the largest radius to judge on (else the sweep stops lower).
MIN_JUDGED = 20


class Padded:
    """A model seen through a wider window: its PSF, zero beyond its own patch."""

    def __init__(self, operator, size: int):
        self.operator, self.psf_size = operator, size
        self.metadata = dict(operator.metadata)
        self._pad = (size - operator.psf_size) // 2

    def psf_at(self, y, x):
        return np.pad(self.operator.psf_at(y, x), self._pad)


def radii_of(visible: float, suggested: float, rmax: float) -> list[float]:
    """The sweep: factors of the visible radius, and the suggestion."""
    return sorted({float(np.ceil(f * visible)) for f in FACTORS if f * visible <= rmax}
                  | {visible, suggested})


def suggestions(image) -> tuple[float, float]:
    """(visible radius, suggested radius) of an image."""
    return suggest_psf_radius(image, wings=1.0), suggest_psf_radius(image)


def sweep(image, name: str) -> list[dict]:
    """Held-out rows of the sweep on one image (one row with a note when it cannot run)."""
    raw = np.asarray(image)
    t0 = time.perf_counter()
    try:
        visible, suggested = suggestions(raw)
    except PsfSpaceError as exc:
        return [{"set": name, "note": f"no radius suggested: {exc}"}]
    radii = radii_of(visible, suggested, min(raw.shape) / 8)
    try:
        need = min(MIN_JUDGED, int(np.count_nonzero(prepare_beads(raw, visible).status == KEPT)))
    except PsfSpaceError as exc:
        return [{"set": name, "note": f"no beads: {exc}"}]
    while True:  # the judging window: the largest radius that leaves enough beads isolated
        big = radii[-1]
        try:
            beads = prepare_beads(raw, big)
            kept = np.flatnonzero(beads.status == KEPT)
        except PsfSpaceError:
            kept = np.zeros(0, int)
        if len(kept) >= need or big <= suggested:
            break
        radii.pop()
    if len(kept) < 2 * FOLDS:
        return [{"set": name, "visible": visible, "suggested": suggested,
                 "note": f"{len(kept)} beads isolated at {big:g} px: too few to cross-fit"}]
    img = beads.clean_image(np.asarray(raw, np.float64))
    hot = spike_mask(img.shape, beads.hot_pixels)
    noise, _ = noise_model_with_source(raw, None, None, None, mask=hot)
    fold_of = assign_folds(beads.positions[kept], img.shape, FOLDS)
    models, trained, stopped = {}, {}, {}
    for r in radii:
        own = beads
        if r != big:  # the beads a user gets at this radius
            try:
                own = prepare_beads(raw, r)
            except PsfSpaceError as exc:
                stopped[r] = str(exc)
                continue
        parts = []
        for f in range(FOLDS):
            held = kept[fold_of == f]
            status = own.status.copy()
            if own is beads:
                status[held] = HELDOUT
            else:  # less those held out
                near = np.linalg.norm(own.positions[:, None] - beads.positions[held][None],
                                      axis=-1).min(axis=1) < 2.0
                status[near & (status == KEPT)] = HELDOUT
            try:
                est = run_with_progress(iter_estimate(img, psf_radius=r,
                                                      beads=own.copy(status),
                                                      holdout=None, motion_test=False))
            except PsfSpaceError as exc:
                stopped[r] = str(exc)
                break
            parts.append((held, est.operator))
        else:
            models[r] = parts
            trained[r] = int(np.count_nonzero(status == KEPT))
    if not models:
        return [{"set": name, "visible": visible, "suggested": suggested,
                 "note": "no radius learnt a model"}]
    window = max(op.psf_size for parts in models.values() for _, op in parts)
    res = {r: BeadResiduals.concatenate([
        fit_beads(img, beads.positions[held], Padded(op, window), noise, fit_radius=big,
                  pixel_mask=hot) for held, op in parts]) for r, parts in models.items()}
    # every bead with signal at every radius (the diagnosis's 'informative' cut, a floor
    # under 10 % of the signal, is for its own windows: in the widest one few pass it)
    judged = np.logical_and.reduce([(x.amplitude > 0) & np.isfinite(x.rel_energy)
                                    for x in res.values()])
    # one signal energy per bead for every radius (the median over the radii of each
    # model's own ||A m||^2): a model's own figure divides by its own fitted signal, which
    # a wider, flatter PSF makes smaller; where noise fills the window (the residual
    # is the noise, whatever the radius) that denominator alone would rank the radii
    resid = {r: (((x.data - x.model) * x.fit_mask) ** 2).sum(axis=(1, 2))
             for r, x in res.items()}
    noise_ss = {r: (x.variance * x.fit_mask).sum(axis=(1, 2)) for r, x in res.items()}
    common = np.median([resid[r] / np.maximum(res[r].rel_energy, 1e-300) for r in res],
                       axis=0)
    per_bead = {r: resid[r][judged] / common[judged] for r in res}
    rows = []
    for r in radii:
        row = {"set": name, "radius": r, "visible": visible, "suggested": suggested,
               "beads": int(judged.sum()), "trained": trained.get(r)}
        if r in res:
            row["error"] = float(np.mean(per_bead[r]))
            row["floor"] = float(np.mean(noise_ss[r][judged] / common[judged]))
            row["own_error"] = float(np.mean(res[r].rel_energy[judged]))
        else:
            row["note"] = f"stopped: {stopped.get(r, '?')}"
        rows.append(row)
    _ratios(rows)
    _interval(rows, per_bead)
    rows[0]["seconds"] = time.perf_counter() - t0
    return rows


def _interval(rows: list[dict], per_bead: dict, n: int = 2000) -> None:
    """The suggestion's ratio to the best radius, 5-95 % over bootstrap resamples of the
    judged beads (paired: the same beads for both), into the suggested row."""
    sug = next((r for r in rows if r["mark"] == "suggested" and "error" in r), None)
    if sug is None:
        return
    best = min((r for r in rows if "error" in r), key=lambda r: r["error"])
    a, b = per_bead[sug["radius"]], per_bead[best["radius"]]
    idx = np.random.default_rng(0).integers(0, len(a), (n, len(a)))
    ratios = a[idx].mean(axis=1) / b[idx].mean(axis=1)
    sug["ratio_lo"], sug["ratio_hi"] = (float(v) for v in np.percentile(ratios, [5, 95]))


def truth_sweep(image, truth, name: str) -> list[dict]:
    """Rows of the sweep on a simulated image: each radius's model (all its beads)
    against the true PSFs on a 6 x 6 grid, over the whole rendered PSF."""
    t0 = time.perf_counter()
    visible, suggested = suggestions(image)
    size = 2 * int(RENDER_RADIUS_FACTOR * truth.psf_radius) + 1
    ys, xs = grid_positions(image.shape, 6)
    true = [truth.psf_at(y, x, size) for y in ys for x in xs]
    rows = []
    for r in radii_of(visible, suggested, (size - 1) / 2 / 1.3):
        row = {"set": name, "radius": r, "visible": visible, "suggested": suggested}
        try:
            est = run_with_progress(iter_estimate(image, psf_radius=r, holdout=None,
                                                  motion_test=False))
        except PsfSpaceError as exc:
            rows.append({**row, "note": f"stopped: {exc}"})
            continue
        op = Padded(est.operator, size)
        row["trained"] = int(est.operator.metadata["n_beads_used"])
        row["error"] = float(np.mean([psf_error(op.psf_at(y, x), t)
                                      for (y, x), t in zip(
                                          [(y, x) for y in ys for x in xs], true,
                                          strict=True)]))
        rows.append(row)
    _ratios(rows)
    rows[0]["seconds"] = time.perf_counter() - t0
    return rows


def _ratios(rows: list[dict]) -> None:
    best = min(row["error"] for row in rows if "error" in row)
    for row in rows:
        if "error" in row:
            row["ratio"] = row["error"] / best
        row["mark"] = ("suggested" if row["radius"] == row["suggested"] else
                       "visible" if row["radius"] == row["visible"] else "")


#: Simulated scenes (seed, aberrations, beads, photons or None for the default, optics
#: code): aberration-free to strong, bright and faint, dense and sparse.
SIMULATED = (
    (0, "moderate", 90, None, "ours"),  # the panel's sample
    (5, "none", 90, None, "ours"),
    (2, "strong", 90, None, "ours"),
    (6, "moderate", 90, 3000.0, "ours"),
    (7, "strong", 30, None, "ours"),
    (0, "moderate", 90, None, "pyotf"),
    (1, "strong", 60, None, "pyotf"),
)


def simulated(generators: list[str]):
    """(name, image, truth) of the simulated scenes."""
    for seed, preset, n, photons, gen in SIMULATED:
        if gen not in generators:
            continue
        kw = {} if photons is None else {"amplitude": (photons, 3 * photons)}
        if gen == "pyotf":
            try:
                kw["optics"] = optics_type("pyotf")()
            except ImportError:
                print("skipped pyotf scenes: pip install -e '.[bench]'")
                return
        image, truth = simulate_beads((768, 768), n, aberrations=preset, seed=seed, **kw)
        label = "sample" if (seed, preset, gen, photons) == (0, "moderate", "ours", None) \
            else f"{gen} {preset} seed {seed}, {n} beads" + (f", {photons:g} ph" if photons
                                                             else "")
        yield label, image, truth


def measured(keys: list[str], step: int):
    """(name, image) of slices of the measured stacks."""
    files = {"sp8": "sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif",
             "astig": "astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif",
             "star": "starfield_2d/dash_starfield_uint16.tif"}
    for key, rel in files.items():
        if key not in keys:
            continue
        path = DATA / rel
        if not path.exists():
            print(f"skipped {key}: {path} not found (../shared/data is not beside the repo)")
            continue
        stack = tifffile.imread(path)
        if stack.ndim == 2:
            yield path.stem, stack
            continue
        for z in range(0, len(stack), step):
            yield f"{path.stem} z={z}", stack[z]


COLUMNS = [("radius", "g"), ("mark", "s"), ("trained", "d"), ("error", ".4g"),
           ("floor", ".4g"), ("own_error", ".4g"), ("ratio", ".3f"), ("note", "s")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", nargs="+", default=["ours", "pyotf", "sp8", "astig", "star"],
                        help="ours / pyotf: simulated scenes; sp8 astig star: measured")
    parser.add_argument("--step", type=int, default=6, help="every step-th slice of a stack")
    args = parser.parse_args()
    OUT.mkdir(exist_ok=True)
    jobs = [(name, image, truth) for name, image, truth in simulated(args.sets)]
    jobs += [(name, image, None) for name, image in measured(args.sets, args.step)]
    summary = []
    with open(OUT / "radius_sweep.jsonl", "w") as out:
        for name, image, truth in jobs:
            rows = sweep(image, name) if truth is None else truth_sweep(image, truth, name)
            for row in rows:
                out.write(json.dumps(row) + "\n")
            if "radius" not in rows[0]:
                print(f"{name}: {rows[0]['note']}")
                summary.append({"set": name, "note": rows[0]["note"][:70]})
                continue
            kind = "truth" if truth is not None else "held-out"
            print(f"\n{name} ({kind}): visible radius {rows[0]['visible']:g} px, suggested "
                  f"{rows[0]['suggested']:g} px, {rows[0].get('beads', '-')} beads judged, "
                  f"{rows[0]['seconds']:.0f} s")
            print(table(rows, COLUMNS))
            ok = [r for r in rows if "error" in r]
            best = min(ok, key=lambda r: r["error"])
            sug = next((r for r in ok if r["radius"] == rows[0]["suggested"]), {})
            vis = next((r for r in ok if r["radius"] == rows[0]["visible"]), {})
            summary.append({"set": name, "kind": kind, "visible": rows[0]["visible"],
                            "suggested": rows[0]["suggested"], "best": best["radius"],
                            "visible_ratio": vis.get("ratio"), "ratio": sug.get("ratio"),
                            "ratio_5_95": (f"{sug['ratio_lo']:.2f}-{sug['ratio_hi']:.2f}"
                                           if "ratio_lo" in sug else None),
                            "floor_over_error": (sug["floor"] / sug["error"]
                                                 if sug.get("floor") else None),
                            "pass": "yes" if (sug.get("ratio") or np.inf) <= TOLERANCE
                            else "NO"})
    print(f"\nSummary: error at the suggested radius / the sweep's best (pass: <= {TOLERANCE});"
          " visible_ratio: the same for the spots' visible radius (the suggestion before)")
    print(table(summary, [("set", "s"), ("kind", "s"), ("visible", "g"), ("suggested", "g"),
                          ("best", "g"), ("visible_ratio", ".3f"), ("ratio", ".3f"),
                          ("ratio_5_95", "s"), ("floor_over_error", ".2f"), ("pass", "s"),
                          ("note", "s")]))


if __name__ == "__main__":
    main()
