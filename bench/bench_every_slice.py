"""Every slice of every measured stack through the estimate and the diagnosis.

A user points the tool at any slice, in focus or not. For every slice of every file in
``../shared/data`` this runs what the command line runs without options: the PSF radius
measured from the slice (:func:`suggest_psf_radius`), :func:`estimate_operator` and
:func:`diagnose`, and records how each ended:

* ``model``: completed;
* ``stopped``: stopped with one of the project's errors (:class:`PsfSpaceError`), whose
  message is recorded;
* ``UNCAUGHT``: any other exception: a bug.

It also records the beads found per slice (detections, kept), so that a count that
doubles on defocused slices shows. Prints a table of outcomes per stack and writes every
row to ``bench/out/every_slice.jsonl``.

    python bench/bench_every_slice.py [--no-diagnose] [--files sp8 astig] [--step 1]
"""

from __future__ import annotations

import argparse
import json
import time
import traceback
from pathlib import Path

import numpy as np
import tifffile

from benchlib import table
from napari_psfspace.core.beads.radius import suggest_psf_radius
from napari_psfspace.core.common.errors import PsfSpaceError
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.diagnosis.loop import diagnose
from napari_psfspace.core.model.estimate import iter_estimate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
OUT = Path(__file__).resolve().parent / "out"


def stacks(keys: list[str] | None):
    for path in sorted(DATA.glob("*/*.tif")):
        if keys and not any(k in path.name for k in keys):
            continue
        yield path


def run(step, fn):
    """(outcome, value or message, seconds)."""
    t = time.perf_counter()
    try:
        value = fn()
        return "model", value, time.perf_counter() - t
    except PsfSpaceError as exc:
        return "stopped", f"{type(exc).__name__}: {exc}", time.perf_counter() - t
    except Exception as exc:  # noqa: BLE001 - what this bench looks for
        return "UNCAUGHT", f"{step}: {type(exc).__name__}: {exc}\n{traceback.format_exc()}", \
            time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", nargs="*", help="substrings of the file names to run")
    ap.add_argument("--step", type=int, default=1, help="every STEP-th slice")
    ap.add_argument("--no-diagnose", action="store_true")
    ap.add_argument("--out", default=str(OUT / "every_slice.jsonl"))
    args = ap.parse_args()
    if not DATA.is_dir():
        raise SystemExit(f"measured data not found at {DATA}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows, summary = [], []
    with out.open("w") as fh:
        for path in stacks(args.files):
            stack = tifffile.imread(path)
            stack = stack if stack.ndim == 3 else stack[None]
            counts: dict[str, int] = {}
            for z in range(0, len(stack), args.step):
                im = stack[z]
                row = {"file": path.name, "slice": z}
                kind, r, t = run("radius", lambda im=im: suggest_psf_radius(im))
                row.update(radius=r if kind == "model" else None, radius_s=t)
                if kind != "model":
                    row.update(estimate=kind, estimate_msg=r, diagnose="-")
                else:
                    kind, est, t = run("estimate", lambda im=im, r=r: run_with_progress(
                        iter_estimate(im, psf_radius=r)))
                    row.update(estimate=kind, estimate_s=t)
                    if kind == "model":
                        c = est.beads.counts()
                        row.update(detected=len(est.beads), kept=c["kept"],
                                   heldout=(est.operator.metadata.get("heldout") or {}).get(
                                       "residual_mean"))
                    else:
                        row["estimate_msg"] = est
                    if not args.no_diagnose:
                        kind, d, t = run("diagnose", lambda im=im, r=r: diagnose(
                            im, psf_radius=r))
                        row.update(diagnose=kind, diagnose_s=t)
                        if kind == "model":
                            v = d.verdict
                            row.update(added=d.added, error_before=d.error_before,
                                       error_after=d.error_after, floor=d.noise_floor,
                                       verdict=v.level, verdict_ratio=v.ratio,
                                       headline=v.headline)
                        else:
                            row["diagnose_msg"] = d
                for key in ("estimate", "diagnose"):
                    k = f"{key} {row.get(key, '-')}"
                    counts[k] = counts.get(k, 0) + 1
                fh.write(json.dumps(row, default=float) + "\n")
                fh.flush()
                rows.append(row)
                print(f"{path.name}[{z}]: r={row['radius']} estimate {row['estimate']} "
                      f"diagnose {row.get('diagnose', '-')} "
                      f"{row.get('estimate_msg', row.get('diagnose_msg', ''))[:150]}",
                      flush=True)
            summary.append({"file": path.name, "slices": len(range(0, len(stack), args.step)),
                            **{k: counts.get(k, 0) for k in (
                                "estimate model", "estimate stopped", "estimate UNCAUGHT",
                                "diagnose model", "diagnose stopped", "diagnose UNCAUGHT")}})
    print()
    print(table(summary, [("file", "s"), ("slices", "d"), ("estimate model", "d"),
                          ("estimate stopped", "d"), ("estimate UNCAUGHT", "d"),
                          ("diagnose model", "d"), ("diagnose stopped", "d"),
                          ("diagnose UNCAUGHT", "d")]))
    bad = [r for r in rows if "UNCAUGHT" in (r.get("estimate"), r.get("diagnose"))]
    for r in bad:
        print(r["file"], r["slice"], r.get("estimate_msg", r.get("diagnose_msg")))
    print(f"\n{len(bad)} slice(s) with an uncaught exception; rows in {out}")
    # what the diagnosis added and its verdict, per file (the verdict's level follows the
    # held-out error over the noise floor: the ratios beside it let a reader check it)
    verdicts = []
    for name in dict.fromkeys(r["file"] for r in rows):
        done = [r for r in rows if r["file"] == name and "verdict" in r]
        if not done:
            continue
        added: dict[str, int] = {}
        for r in done:
            for e in r["added"] or ["-"]:
                added[e] = added.get(e, 0) + 1
        for level in ("explained", "partly explained", "not explained"):
            rs = [r for r in done if r["verdict"] == level]
            if rs:
                ratios = [r["verdict_ratio"] for r in rs]
                verdicts.append({"file": name, "verdict": level, "slices": len(rs),
                                 "ratio_min": float(np.nanmin(ratios)),
                                 "ratio_max": float(np.nanmax(ratios))})
        verdicts.append({"file": name, "verdict": "added: " + ", ".join(
            f"{k} {v}" for k, v in added.items()), "slices": len(done)})
    if verdicts:
        print()
        print(table(verdicts, [("file", "s"), ("verdict", "s"), ("slices", "d"),
                               ("ratio_min", ".2f"), ("ratio_max", ".2f")]))


if __name__ == "__main__":
    main()
