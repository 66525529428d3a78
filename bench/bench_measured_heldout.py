"""Held-out beads of every measured slice, judged on their raw pixels: this checkout
against another.

    python bench/bench_measured_heldout.py [--baseline SRC] [--step 1]

On every ``--step``-th slice of the measured bead stacks and on the star field
(``../shared/data``), at the radius the tool suggests for the slice: a fifth of the beads
is held out (the estimator's own split), a model is fitted to the rest, and each held-out
bead is judged on its raw pixels within the patch's radius: the norm of what is left
after a plane and the model's PSF at the bead (sub-pixel shifted) are fitted together,
over the norm of what a plane alone leaves. The plane is fitted with the model here, so
the figure does not depend on how either checkout takes out the background. A slice with
too few beads for a split, or that the tool refuses, is counted, not judged.
``--baseline SRC``: the same with another checkout's ``src`` in a subprocess, and the
paired differences per slice.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import tifffile
from scipy import ndimage as ndi

from benchlib import table

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SETS = {"sp8": "sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif",
        "astigmatic": "astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif",
        "stars": "starfield_2d/dash_starfield_uint16.tif"}


def judge(img, op, centers, size) -> np.ndarray:
    """Each bead's raw residual with a plane and the model's PSF fitted together, over
    the residual of the plane alone, shape (K,)."""
    from napari_psfspace.core.beads.centering import gather_windows

    half = size // 2
    wins = gather_windows(img, centers, half).astype(float)
    d = np.arange(size) - half
    yy, xx = np.meshgrid(d, d, indexing="ij")
    inside = (np.hypot(yy, xx) <= half).ravel()
    out = []
    for k, c in enumerate(centers):
        m = ndi.shift(op.psf_at(*c), c - np.round(c), order=3, mode="constant")
        a = np.stack([np.ones(size * size), xx.ravel(), yy.ravel(), m.ravel()], 1)[inside]
        y = wins[k].ravel()[inside]
        full = y - a @ np.linalg.lstsq(a, y, rcond=None)[0]
        plane = y - a[:, :3] @ np.linalg.lstsq(a[:, :3], y, rcond=None)[0]
        out.append(np.linalg.norm(full) / max(np.linalg.norm(plane), 1e-300))
    return np.array(out)


def slice_score(image) -> tuple[float | None, str]:
    from napari_psfspace.core.beads.radius import suggest_psf_radius
    from napari_psfspace.core.common.validate import as_image
    from napari_psfspace.core.model import estimate
    from napari_psfspace.core.model.heldout import split_holdout
    from napari_psfspace.core.model.patch_fit import fit_patches

    try:
        r = float(suggest_psf_radius(image))
        raw = np.asarray(image)
        beads, img = estimate.find_usable_beads(raw, as_image(raw), r, beads=None,
                                                threshold=8.0, saturation=None)
        kept = estimate.centre_beads(img, beads, r)
        kept, p, _ = estimate.usable_patches(img, beads, kept, r)
        held = split_holdout(p.centers, img.shape, 0.2)
        if np.count_nonzero(~held) < 8 or np.count_nonzero(held) < 2:
            return None, "too few beads"
        _, op, _, _ = fit_patches(p.subset(~held), img.shape)
        return float(np.median(judge(img, op, p.centers[held], p.size))), "judged"
    except (ValueError, TypeError) as exc:
        return None, type(exc).__name__


def measure(step: int) -> dict:
    out = {}
    for name, rel in SETS.items():
        stack = tifffile.imread(DATA / rel)
        planes = [stack] if stack.ndim == 2 else list(stack[::step])
        out[name] = [slice_score(p) for p in planes]
        print(name, "done", file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", default=None, help="another checkout's src, beside")
    ap.add_argument("--step", type=int, default=1)
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if not DATA.exists():
        raise SystemExit(f"needs the measured data in {DATA}")
    here = measure(args.step)
    if args.json:
        print(json.dumps(here))
        return
    base = None
    if args.baseline:
        env = {**os.environ, "PYTHONPATH": str(Path(args.baseline).resolve())}
        cmd = [sys.executable, __file__, "--json", "--step", str(args.step)]
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        base = json.loads(done.stdout.strip().splitlines()[-1])
    rows = []
    for name, scores in here.items():
        mine = np.array([np.nan if s is None else s for s, _ in scores])
        row = {"set": name, "slices": len(scores), "judged": int(np.isfinite(mine).sum()),
               "this": float(np.nanmean(mine))}
        if base is not None:
            theirs = np.array([np.nan if s is None else s for s, _ in base[name]])
            both = np.isfinite(mine) & np.isfinite(theirs)
            d = mine[both] - theirs[both]
            row.update(baseline=float(np.mean(theirs[both])), both=int(both.sum()),
                       diff=float(d.mean()),
                       se=float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else 0.0,
                       worst=float(d.max()) if len(d) else 0.0)
        rows.append(row)
    print("Held-out measured beads: raw residual with a plane and the model's PSF, over "
          "a plane's alone (median per slice, mean over slices; diff = this - baseline "
          "on the slices both judged)")
    cols = [("set", "s"), ("slices", "d"), ("judged", "d"), ("this", ".4f")]
    if base is not None:
        cols += [("both", "d"), ("baseline", ".4f"), ("diff", ".4f"), ("se", ".4f"),
                 ("worst", ".4f")]
    print(table(rows, cols))


if __name__ == "__main__":
    main()
