"""diagnose on simulated images: false alarms on effect-free images, and each effect.

    python bench/bench_diagnose.py [--seeds 20] [--size 640]

Prints (1) for effect-free images (moderate / strong / none aberrations in turn), what
diagnose added (the issue's target: nothing in >= 95 % of seeds), and (2) for each
simulated effect, what was added and the held-out error before and after.
"""

from __future__ import annotations

import argparse
import time

from benchlib import table
from napari_psfspace.core.diagnosis.loop import diagnose
from napari_psfspace.core.simulation import simulate_beads

#: case -> (simulated effects, other simulate_beads options)
EFFECTS = {
    "hot pixels": ({"hot_pixels": 40}, {}),
    "row+column offsets": ({"row_offsets": 8.0, "column_offsets": 8.0}, {}),
    "saturation": ({"saturation": 3000}, {}),
    "nonlinearity": ({"nonlinearity": 0.3}, {}),
    "neighbours": ({"neighbours": 0.3}, {}),
    "bead size": ({"bead_size": (0.1, 0.5)}, {}),
    "drift": ({"drift": (3.0, 0.0)}, {}),
    # beads of similar brightness (+-14 %): with a 3x spread (the default) a 0.5
    # fall-off is not detectable from 70 beads (amplitude_field z = 2.2 and 0.7)
    "illumination": ({"illumination": 0.5}, {"amplitude": (3e4, 4e4)}),
    "background structure": ({"background_structure": 60.0}, {}),
    "hot pixels + offsets": ({"hot_pixels": 40, "row_offsets": 8.0}, {}),
    "illumination + nonlinearity": ({"illumination": 0.5, "nonlinearity": 0.3},
                                    {"amplitude": (3e4, 4e4)}),
}
PRESETS = ("moderate", "strong", "none")
COLUMNS = [("case", "s"), ("seed", "d"), ("aberrations", "s"), ("added", "s"),
           ("error_before", ".4f"), ("error_after", ".4f"), ("floor", ".4f"),
           ("chi2_before", ".2f"), ("chi2_after", ".2f"), ("photometric", "s"),
           ("seconds", ".1f")]


def run(case, effects, seed, size, n_beads, **options):
    preset = PRESETS[seed % 3]
    image, truth = simulate_beads((size, size), n_beads, aberrations=preset, seed=seed,
                                  effects=effects, **options)
    t0 = time.perf_counter()
    d = diagnose(image, psf_radius=truth.psf_radius)
    phot = "-"
    for st in d.steps:
        cmp = st.params.get("_comparison", {}) if st.accepted else {}
        if "photometric_before" in cmp:
            phot = f"{cmp['photometric_before']:.4f}->{cmp['photometric_after']:.4f}"
    zs = {t.name: t.strength for t in d.analysis_before.tests.values()}
    return {"_z": zs, "photometric": phot, "case": case, "seed": seed, "aberrations": preset,
            "added": ", ".join(d.added) or "-", "error_before": d.error_before,
            "error_after": d.error_after, "floor": d.noise_floor,
            "chi2_before": d.chi2_before, "chi2_after": d.chi2_after,
            "seconds": time.perf_counter() - t0}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--size", type=int, default=640)
    ap.add_argument("--beads", type=int, default=70)
    ap.add_argument("--skip-effects", action="store_true")
    args = ap.parse_args()
    rows = [run("effect-free", None, s, args.size, args.beads) for s in range(args.seeds)]
    clean = sum(r["added"] == "-" for r in rows)
    print(f"Effect-free images: nothing added in {clean}/{len(rows)} seeds "
          f"({100 * clean / len(rows):.0f} %; target >= 95 %)")
    print(table(rows, COLUMNS), flush=True)
    from napari_psfspace.core.diagnosis.analysis import THRESHOLDS, TREND_VARIABLES

    names = sorted(rows[0]["_z"])
    th = {n: THRESHOLDS["trend" if n.startswith("trend_") else n] for n in names}
    zrows = [{"test": n, "threshold": th[n], "max_z": max(r["_z"][n] for r in rows),
              "seeds_above": sum(r["_z"][n] > th[n] for r in rows)} for n in names]
    print(f"\nNull calibration: largest |z| of each test over the {len(rows)} effect-free "
          f"seeds (trend variables: {', '.join(TREND_VARIABLES)})")
    print(table(zrows, [("test", "s"), ("threshold", ".1f"), ("max_z", ".2f"),
                        ("seeds_above", "d")]), flush=True)
    if args.skip_effects:
        return
    print("\nEach simulated effect (seeds 0, 1, 2: moderate, strong, no aberrations)")
    rows = []
    for name, (fx, options) in EFFECTS.items():
        for s in (0, 1, 2):
            rows.append(run(name, fx, s, args.size, args.beads, **options))
            print(table(rows[-1:], COLUMNS).splitlines()[-1], flush=True)
    print(table(rows, COLUMNS))


if __name__ == "__main__":
    main()
