"""diagnose over the seeded scene set: false alarms on effect-free scenes.

    python bench/bench_family.py [--scenes 100] [--workers 2]

Each scene is drawn by
:func:`~napari_psfspace.core.simulation.scene_set.random_scene` (512 x 512; pixel
size 43-160 nm, NA 0.7-1.49, emission 450-700 nm, aberration presets and random fields,
20-600 beads, brightness spread sigma 0.1-1.0, background 1-500 photons, camera gain,
offset, read noise, 8/12/16-bit) with no effect injected, and diagnosed with the true PSF
radius. A false alarm is an effect about the data added that the scene does not hold
(saturation is held where the scene clipped at full scale); a change of the model's
settings (:data:`MODEL_SETTINGS`) is counted apart, with the field error against the
truth before and after it. Scenes where diagnose refuses (too few usable beads, every
bead saturated) are counted apart. Prints one line per scene and a summary:
the false-alarm rate, which effects were added, which residual tests fired most, and
each test's calibration on the still scenes (share fired, 95th percentile and maximum
of its statistic).
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from benchlib import table
from napari_psfspace.core.diagnosis.loop import diagnose
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.scene_set import random_scene

#: Effects that change the model's settings (its capacity), not a claim about the data.
MODEL_SETTINGS = ("basis_size", "field_smoothing")


def run(seed: int) -> dict:
    image, truth, p = random_scene(seed)
    t0 = time.perf_counter()
    row = {"seed": seed, "aberrations": p["aberrations"], "bits": p["bits"],
           "beads": p["n_beads"], "pixel_nm": 1000 * p["pixel_size"],
           "peak_photons": p["peak_photons"], "background": p["background"]}
    try:
        d = diagnose(image, psf_radius=truth.psf_radius)
    except ValueError as err:
        return {**row, "added": "refused", "alarms": "", "fired": "",
                "note": str(err)[:60], "seconds": time.perf_counter() - t0}
    fired = [t.name for t in d.analysis_before.tests.values() if t.significant]
    row["strength"] = {t.name: (float(t.strength), float(t.threshold))
                       for t in d.analysis_before.tests.values()}
    # saturation is no false alarm where the scene clipped (bright beads of a 12-bit or
    # 8-bit scene reach full scale); model settings are no claim about the data
    present = {"saturation"} if int((image >= p["full_scale"]).sum()) > 0 else set()
    alarms = [e for e in d.added if e not in MODEL_SETTINGS and e not in present]
    settings = [e for e in d.added if e in MODEL_SETTINGS]
    row.update(saturated_px=int((image >= p["full_scale"]).sum()),
               added=", ".join(d.added) or "-", alarms=", ".join(alarms) or "-",
               fired=", ".join(fired), error_before=d.error_before, floor=d.noise_floor,
               note="")
    if settings:  # did the model's change bring it closer to the truth?
        plain = estimate_operator(image, psf_radius=truth.psf_radius)
        row["truth_plain"] = float(np.mean(grid_errors(plain, truth, n=6)))
        row["truth_final"] = float(np.mean(grid_errors(d.operator, truth, n=6)))
    row["seconds"] = time.perf_counter() - t0
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--first", type=int, default=0, help="first seed")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    seeds = range(args.first, args.first + args.scenes)
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(run, seeds))
    cols = [("seed", "d"), ("aberrations", "s"), ("bits", "d"), ("beads", "d"),
            ("pixel_nm", ".0f"), ("peak_photons", ".0f"), ("background", ".0f"),
            ("saturated_px", "d"), ("added", "s"), ("alarms", "s"), ("error_before", ".4f"),
            ("floor", ".4f"), ("truth_plain", ".4f"), ("truth_final", ".4f"),
            ("fired", "s"), ("seconds", ".1f")]
    print(table(rows, cols))
    done = [r for r in rows if r["added"] != "refused"]
    alarms = [r for r in done if r["alarms"] != "-"]
    anything = [r for r in done if r["added"] != "-"]
    added = Counter(e for r in anything for e in r["added"].split(", "))
    fired = Counter(t for r in done for t in r["fired"].split(", ") if t)
    changed = [r for r in done if "truth_plain" in r]
    n = max(len(done), 1)
    print(f"\n{len(done)} scenes diagnosed ({len(rows) - len(done)} refused: too few usable "
          f"beads); false alarms (an effect about the data added that the scene does not "
          f"hold): {len(alarms)} ({100 * len(alarms) / n:.1f} %); anything added: "
          f"{len(anything)} ({100 * len(anything) / n:.1f} %)")
    print("effects added:", dict(added.most_common()) or "none")
    if changed:
        better = sum(r["truth_final"] < r["truth_plain"] for r in changed)
        print(f"model settings changed on {len(changed)} scenes; the field error against "
              f"the truth dropped on {better}: " + ", ".join(
                  f"{r['seed']}: {r['truth_plain']:.4f} -> {r['truth_final']:.4f}"
                  for r in changed))
    print("residual tests significant on the plain model:", dict(fired.most_common()))
    # each test's calibration on the still scenes: share fired, 95th percentile, maximum
    print()
    names = sorted({n for r in done for n in r.get("strength", {})})
    calib = []
    for n in names:
        v = np.array([r["strength"][n][0] for r in done if n in r.get("strength", {})])
        th = next(r["strength"][n][1] for r in done if n in r.get("strength", {}))
        calib.append({"test": n, "threshold": th, "fired": float(np.mean(v > th)),
                      "p95": float(np.quantile(v, 0.95)), "max": float(v.max())})
    print(table(calib, [("test", "s"), ("threshold", ".2f"), ("fired", ".2f"),
                        ("p95", ".2f"), ("max", ".2f")]))


if __name__ == "__main__":
    main()
