"""How many of the beads a person would pick the estimate uses (issue 45, point 3).

    python bench/bench_beads_used.py [--generator ours pyotf psfmodels] [--seeds 20 21]
                                     [--rules 2r energy] [--wide] [--min-separation 1]
    python bench/bench_beads_used.py --measured

A bead a person would pick (the issue's definition), from the scene's truth: its centre
at least ``r`` (the scene's PSF radius) from the image's edge, and its neighbours adding
under 5 % of the energy in its patch (radius ``1.2 r``): the sum over the other beads of
their photons times the share of a PSF (the true PSF at the field's centre) that falls
in the disk, over the bead's own. ``pickable``: those whose core (``r / 3``) is below
the camera's clipping level (neither saturated nor in a clipped background: no PSF can be
read from them) and whose brightest pixel stands 3 noise sd above the background (the
true PSF's peak times the bead's photons, against the background's photon noise and the
read noise): a bead a person can see. ``used``: the beads in the final fit
(``metadata["bead_positions"]``), matched to the truth within 2 px; ``saturated``: the
detections the estimate set aside as saturated (the definition does not exclude them).
Scenes: the family's draws (``random_scene``), 512 x 512, or ``--wide`` 2048 x 2048 with 400 beads;
``--min-separation 1`` crowds them (the family keeps centres 2.5 radii apart).
``--rules``: the neighbour rule, ``2r`` (the paper's: no detection within ``2 r``) or
``energy`` (the default since issue 45: the neighbours add under 5 % of the patch's
energy, ``core/beads/overlap.py``), or ``default`` (the code's own, untouched: run with
``PYTHONPATH=<old checkout>/src`` for the code before a change); ``error``: the field's
mean aligned relative error on an 8 x 8 grid against the true PSFs
(``simulation.metrics.grid_errors``).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import cKDTree

from benchlib import optics_type, table
from napari_psfspace.core.beads import detect
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.scene_set import random_scene

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


def estimate(image, r: float, rule: str):
    """The estimate under one neighbour rule (the defaults of the detection's two doors);
    ``default``: the code's own defaults, untouched (also for a baseline's code)."""
    if rule == "default":
        return estimate_operator(image, psf_radius=r)
    saved = (detect.detect_beads.__kwdefaults__["neighbour_share"],
             detect.flag_unusable.__kwdefaults__["neighbour_share"])
    share = None if rule == "2r" else saved[1]
    detect.detect_beads.__kwdefaults__["neighbour_share"] = share
    detect.flag_unusable.__kwdefaults__["neighbour_share"] = share
    try:
        return estimate_operator(image, psf_radius=r)
    finally:
        detect.detect_beads.__kwdefaults__["neighbour_share"] = saved[0]
        detect.flag_unusable.__kwdefaults__["neighbour_share"] = saved[1]


def count(generator: str, seed: int, wide: bool, min_separation: float | None = None,
          rules=("energy",)) -> list[dict]:
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
    # a bead whose core is at the camera's clipping level (a saturated bead, or one in a
    # clipped background) gives no PSF: a person would not pick it
    clip = float(np.iinfo(image.dtype).max) if image.dtype.kind in "ui" else np.inf
    core = max(1, int(round(r / 3)))
    iy = np.clip(np.round(pos[:, 0]).astype(int), 0, h - 1)
    ix = np.clip(np.round(pos[:, 1]).astype(int), 0, w - 1)
    top = np.array([image[max(y - core, 0): y + core + 1, max(x - core, 0): x + core + 1].max()
                    for y, x in zip(iy, ix, strict=True)])
    # and one a person can see: its brightest pixel 3 noise sd above the background
    # (photons: the background's and the read noise's)
    noise = np.sqrt(float(p["background"]) + float(p.get("read_noise", 0.0)) ** 2)
    visible = amp * float(psf.max()) >= 3.0 * noise
    pickable = isolated & (top < clip) & visible
    rows = []
    for rule in rules:
        row = {"gen": generator, "seed": seed, "rule": rule, "beads": len(pos),
               "isolated": int(isolated.sum()), "pickable": int(pickable.sum())}
        rows.append(row)
        try:
            op = estimate(image, truth.psf_radius, rule)
        except ValueError as exc:
            row["note"] = str(exc)[:50]
            continue
        used_pos = np.asarray(op.metadata["bead_positions"], float).reshape(-1, 2)
        d, idx = tree.query(used_pos) if len(used_pos) else (np.zeros(0), np.zeros(0, int))
        used = np.zeros(len(pos), bool)
        used[idx[d <= 2.0]] = True
        row.update({"used": int(len(used_pos)), "used_isolated": int((used & isolated).sum()),
                    "used_pickable": int((used & pickable).sum()),
                    "saturated": int(op.metadata["bead_counts"].get("saturated", 0)),
                    "error": float(np.mean(grid_errors(op, truth, n=8)))})
        row["share"] = row["used_isolated"] / max(row["isolated"], 1)
        if row["pickable"]:
            row["share_pickable"] = row["used_pickable"] / row["pickable"]
    return rows


#: ``--measured``: slices of the measured stacks, the PSF radius 0.5 um
MEASURED = (("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif", (20, 32, 44)),
            ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif", (28, 33, 38)))


def measured(data) -> None:
    """Beads detected and used on slices of the measured stacks (no truth: the counts)."""
    from napari_psfspace.io import read_image

    rows = []
    for path, slices in MEASURED:
        for z in slices:
            img, info = read_image(data / path, index=z)
            op = estimate_operator(img, psf_radius=0.5 / info.pixel_size)
            counts = op.metadata["bead_counts"]
            rows.append({"set": path.split("/")[0], "slice": z,
                         "detected": int(sum(counts.values())),
                         "used": int(op.metadata["n_beads_used"]),
                         "neighbour": int(counts.get("neighbour", 0)),
                         "border": int(counts.get("border", 0))})
            print(rows[-1], flush=True)
    print(table(rows, [("set", "s"), ("slice", "d"), ("detected", "d"), ("used", "d"),
                       ("neighbour", "d"), ("border", "d")]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--generator", nargs="+", default=["ours", "pyotf", "psfmodels"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[20, 21, 22, 23, 24])
    ap.add_argument("--wide", action="store_true")
    ap.add_argument("--min-separation", type=float, default=None,
                    help="bead centres at least this many PSF radii apart (the family "
                         "draws 2.5: well-separated beads); 1.0 gives crowded fields")
    ap.add_argument("--rules", nargs="+", default=["default"],
                    choices=["default", "2r", "energy"])
    ap.add_argument("--measured", action="store_true",
                    help="beads detected and used on slices of ../shared/data's stacks")
    args = ap.parse_args()
    if args.measured:
        from pathlib import Path

        measured(Path(__file__).resolve().parents[2] / "shared" / "data")
        return
    rows = []
    for gen in args.generator:
        for seed in args.seeds:
            rows += count(gen, seed, args.wide, args.min_separation, args.rules)
            for row in rows[-len(args.rules):]:
                print(row, flush=True)
    print(f"\nIsolated beads (centre >= r from the edge, neighbours < {SHARE:.0%} of the "
          "patch's energy) and how many the estimate uses")
    print(table(rows, [("gen", "s"), ("seed", "d"), ("rule", "s"), ("beads", "d"),
                       ("isolated", "d"), ("used", "d"), ("used_isolated", "d"),
                       ("share", ".2f"), ("pickable", "d"), ("share_pickable", ".2f"),
                       ("saturated", "d"), ("error", ".4f")]))
    if len(args.rules) == 2:
        a, b = args.rules
        ratio = []
        for x, y in zip(rows[::2], rows[1::2], strict=True):
            if x.get("error") and y.get("error"):
                ratio.append(y["error"] / x["error"])
        if ratio:
            r = np.array(ratio)
            se = r.std(ddof=1) / np.sqrt(len(r)) if len(r) > 1 else 0.0
            print(f"\nerror {b} / {a}: mean {r.mean():.3f} (SE {se:.3f}), worst {r.max():.3f}, "
                  f"best {r.min():.3f}, n {len(r)}")


if __name__ == "__main__":
    main()
