"""Does a defocus gradient cost what the data lose, or what the model misses? (issue 23)

    python bench/bench_gradient_oracle.py [--seeds 7] [--photons 100]

For a scene of ``bench_power.py``'s setting (1024 x 1024, 150 beads, moderate field
aberrations, the rest drawn from the family), the field error of ``estimate_operator`` at
the true radius (6 x 6 grid, aligned) without and with a defocus gradient of 0.15 waves
rms across the field, as drawn and again with the signal taken out of the way: ``x P``
the photons and background at 16 bits, and ``x P`` the photons at the drawn bit depth with
the gain cut ``P`` times (the same ADU image, so the same quantisation). The scene's draw
(optics, beads, their positions) is the same in every row.
"""

from __future__ import annotations

import argparse

import numpy as np

from bench_power import SETTING
from benchlib import table
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.scene_set import random_scene


def rows_for(seed: int, photons: float) -> list[dict]:
    _, _, p = random_scene(seed, **SETTING)
    more = {"peak_photons": float(p["peak_photons"]) * photons,
            "background": float(p["background"]) * photons}
    variants = [("as drawn", {}), (f"x{photons:g} photons, 16 bit", {**more, "bits": 16}),
                (f"x{photons:g} photons, gain / {photons:g}",
                 {**more, "gain": float(p["gain"]) / photons})]
    rows = []
    for name, over in variants:
        errs = []
        for eff in (None, {"defocus_gradient": 0.15}):
            image, truth, _ = random_scene(seed, effects=eff, **{**SETTING, **over})
            op = estimate_operator(image, psf_radius=truth.psf_radius)
            errs.append(float(np.mean(grid_errors(op, truth, n=6))))
        rows.append({"seed": seed, "signal": name, "bits": int(over.get("bits", p["bits"])),
                     "without": errs[0], "with": errs[1], "ratio": errs[1] / errs[0]})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[7])
    ap.add_argument("--photons", type=float, default=100.0)
    args = ap.parse_args()
    rows = [r for seed in args.seeds for r in rows_for(seed, args.photons)]
    print(table(rows, [("seed", "d"), ("signal", "s"), ("bits", "d"), ("without", ".4f"),
                       ("with", ".4f"), ("ratio", ".2f")]))


if __name__ == "__main__":
    main()
