"""How many of the beads a person would pick the estimate uses (issue 45, point 3).

    python bench/bench_beads_used.py [--generator ours pyotf psfmodels] [--seeds 20 21]

A bead a person would pick (the issue's definition), from the scene's truth: its centre
at least ``r`` (the scene's PSF radius) from the image's edge, and its neighbours adding
under 5 % of the energy in its patch (radius ``1.2 r``): the sum over the other beads of
their photons times the share of a PSF (the true PSF at the field's centre) that falls
in the disk, over the bead's own. ``used``: the beads in the final fit
(``metadata["bead_positions"]``), matched to the truth within 2 px; ``saturated``: the
detections the estimate set aside as saturated (the definition does not exclude them).
Scenes: the family's draws (``random_scene``), 512 x 512, or ``--wide`` 2048 x 2048 with 400 beads;
``--min-separation 1`` crowds them (the family keeps centres 2.5 radii apart).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import cKDTree

from _common import optics_type, table
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.simulation.family import random_scene

SHARE = 0.05


def disk_energy(psf: np.ndarray, radius: float, distances: np.ndarray) -> np.ndarray:
    """Energy of ``psf`` (centred, sum 1 over its window) inside a disk of ``radius``
    whose centre lies ``d`` pixels from the PSF's (along the columns), for each ``d``."""
    n = psf.shape[0]
    c = n // 2
    yy, xx = np.mgrid[:n, :n] - c
    out = np.empty(len(distances))
    for i, d in enumerate(distances):
        out[i] = psf[(yy ** 2 + (xx - d) ** 2) <= radius ** 2].sum()
    return out


def count(generator: str, seed: int, wide: bool, min_separation: float | None = None
          ) -> dict:
    kw = {"shape": (2048, 2048), "n_beads": 400, "aberrations": "strong", "na": 1.3,
          "peak_photons": (2000.0, 20000.0), "background": (5.0, 50.0), "bits": 16} if wide \
        else {}
    if min_separation is not None:
        kw["min_separation"] = min_separation
    image, truth, p = random_scene(seed, optics_type=optics_type(generator), **kw)
    r = float(truth.psf_radius)
    big = int(2 * np.ceil(3.6 * r)) + 1
    h, w = truth.shape
    psf = truth.psf_at((h - 1) / 2, (w - 1) / 2, size=big)
    psf = psf / psf.sum()
    rad = 1.2 * r
    dist = np.arange(0, big // 2 + 1)
    energy = disk_energy(psf, rad, dist)
    pos, amp = truth.positions, truth.amplitudes
    tree = cKDTree(pos)
    inside = ((pos[:, 0] >= r) & (pos[:, 1] >= r) & (pos[:, 0] <= h - 1 - r)
              & (pos[:, 1] <= w - 1 - r))
    share = np.zeros(len(pos))
    for m, nb in enumerate(tree.query_ball_point(pos, dist[-1])):
        for n in nb:
            if n != m:
                d = int(round(np.hypot(*(pos[n] - pos[m]))))
                share[m] += amp[n] * energy[min(d, len(energy) - 1)]
        share[m] /= amp[m] * energy[0]
    isolated = inside & (share < SHARE)
    row = {"gen": generator, "seed": seed, "beads": len(pos), "isolated": int(isolated.sum())}
    try:
        op = estimate_operator(image, psf_radius=truth.psf_radius)
    except ValueError as exc:
        row["note"] = str(exc)[:50]
        return row
    used_pos = np.asarray(op.metadata["bead_positions"], float).reshape(-1, 2)
    d, idx = tree.query(used_pos) if len(used_pos) else (np.zeros(0), np.zeros(0, int))
    used = np.zeros(len(pos), bool)
    used[idx[d <= 2.0]] = True
    row.update({"used": int(len(used_pos)), "used_isolated": int((used & isolated).sum()),
                "saturated": int(op.metadata["bead_counts"].get("saturated", 0))})
    row["share"] = row["used_isolated"] / max(row["isolated"], 1)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--generator", nargs="+", default=["ours", "pyotf", "psfmodels"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[20, 21, 22, 23, 24])
    ap.add_argument("--wide", action="store_true")
    ap.add_argument("--min-separation", type=float, default=None,
                    help="bead centres at least this many PSF radii apart (the family "
                         "draws 2.5: well-separated beads); 1.0 gives crowded fields")
    args = ap.parse_args()
    rows = []
    for gen in args.generator:
        for seed in args.seeds:
            rows.append(count(gen, seed, args.wide, args.min_separation))
            print(rows[-1], flush=True)
    print(f"\nIsolated beads (centre >= r from the edge, neighbours < {SHARE:.0%} of the "
          "patch's energy) and how many the estimate uses")
    print(table(rows, [("gen", "s"), ("seed", "d"), ("beads", "d"), ("isolated", "d"),
                       ("used", "d"), ("used_isolated", "d"), ("share", ".2f"),
                       ("saturated", "d")]))


if __name__ == "__main__":
    main()
