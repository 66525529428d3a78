"""A crowded field's light the model cannot draw: each kept bead's patch error against the
truth by how much neighbours' light the deblend took out of it, and the light in its window
from beads beyond the model's reach.

    python bench/bench_neighbour_reach.py [--seed 0] [--beads 300 600]
                                          [--gradient 0.15] [--separation 30]

The noise-free gradient scenes of ``bench_more_beads.py``. The deblend
(``core.model.deblend``) draws each neighbour with the model's PSF, which is defined only
inside its window (``1.2 r``): a neighbour farther than ``2.4 r`` never reaches a patch's
window in the model, but its PSF's tails reach it in the image. For each kept bead of the
estimate, matched to the nearest true bead:

- ``taken``: the neighbours' light the deblend's last pass took out of its window, over
  its own light there, binned;
- ``error``: the median relative l2 distance of its sum-1 patch from the true PSF at its
  true position, windowed the same way and moved to the estimate's centre (quintic
  spline);
- ``beyond``: the median light in its window of the true beads farther than ``2.4 r``,
  over its own light there (both rendered by the simulator, to ``3 r``).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from bench_estimator_ladder import scene
from benchlib import table
from napari_psfspace.core.beads.window import bump_window
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model import deblend
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.simulation.render import render_beads
from napari_psfspace.core.simulation.scene import RENDER_RADIUS_FACTOR

BINS = ((0.0, 0.005), (0.005, 0.02), (0.02, 0.05), (0.05, np.inf))
REACH = 2.4  # PSF radii: two windows' radii, the farthest a modelled neighbour reaches


def local_light(truth, which, center, size, window) -> float:
    """The light of the true beads ``which`` inside ``window`` (size x size) about
    ``center``, rendered on a canvas about it as the scene is."""
    r = truth.psf_radius
    half = int(np.ceil((RENDER_RADIUS_FACTOR + 1.2) * r)) + 2
    base = np.round(center) - half
    canvas = np.zeros((2 * half + 1, 2 * half + 1))
    if len(which):
        render_beads(canvas, truth.positions[which] - base, truth.amplitudes[which],
                     truth.aberrations, truth.optics, RENDER_RADIUS_FACTOR * r)
    grid = np.mgrid[0:size, 0:size].reshape(2, -1) + (center - base - size // 2)[:, None]
    cut = ndi.map_coordinates(canvas, grid, order=1).reshape(size, size)
    return float((cut * window).sum())


def taken_light(light, patches, window) -> np.ndarray:
    """The neighbours' light ``light`` draws in each patch's window, over the patch's own
    light there (0 without a deblend)."""
    if light is None:
        return np.zeros(len(patches))
    off = np.arange(patches.size, dtype=np.float64) - patches.size // 2
    grid = np.stack(np.meshgrid(off, off, indexing="ij"), -1).reshape(-1, 2)
    return np.array([(light.around(c, c + grid).reshape(window.shape) * window).sum() / f
                     for c, f in zip(patches.centers, patches.flux, strict=True)])


def estimate_with_light(image, psf_radius: float):
    """The estimate, and the deblend's :class:`ModelLight` of each pass."""
    lights = []
    shipped = deblend.model_light

    def keep(*args, **kwargs):
        lights.append(shipped(*args, **kwargs))
        return lights[-1]

    deblend.model_light = keep
    try:
        return run_with_progress(iter_estimate(image, psf_radius=psf_radius)), lights
    finally:
        deblend.model_light = shipped


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--beads", type=int, nargs="+", default=[300, 600])
    ap.add_argument("--gradient", type=float, default=0.15)
    ap.add_argument("--separation", type=float, default=30.0)
    args = ap.parse_args()
    rows = []
    for n in args.beads:
        image, truth = scene(args.seed, args.gradient, False, n, args.separation)
        est, lights = estimate_with_light(image, truth.psf_radius)
        p, r = est.patches, truth.psf_radius
        _, match = cKDTree(truth.positions).query(p.centers)
        window = bump_window(p.size, p.r, p.r_ext)
        tree = cKDTree(truth.positions)
        err, beyond = np.zeros(len(match)), np.zeros(len(match))
        for i, j in enumerate(match):
            t = truth.positions[j]
            true = truth.psf_at(*t, p.size) * window
            true = ndi.shift(true / true.sum(), t - p.centers[i], order=5, mode="constant")
            true /= true.sum()
            err[i] = np.linalg.norm(p.psf[i] - true) / np.linalg.norm(true)
            near = tree.query_ball_point(t, (RENDER_RADIUS_FACTOR + 1.2) * r)
            far = [m for m in near if np.hypot(*(truth.positions[m] - t)) > REACH * r]
            own = local_light(truth, [j], t, p.size, window)
            beyond[i] = local_light(truth, far, t, p.size, window) / own
        taken = taken_light(lights[-1] if lights else None, p, window)
        for lo, hi in BINS:
            m = (taken >= lo) & (taken < hi)
            if m.any():
                rows.append({"beads": n, "taken": f"{lo:g}-{hi:g}", "kept": int(m.sum()),
                             "error": float(np.median(err[m])),
                             "beyond": float(np.median(beyond[m]))})
                print(rows[-1], flush=True)
        rows.append({"beads": n, "taken": "all", "kept": len(match),
                     "error": float(np.median(err)), "beyond": float(np.median(beyond))})
        print(rows[-1], flush=True)
    print(f"\nA crowded field's light beyond the model's reach ({REACH:g} r), noise-free, "
          f"gradient +-{args.gradient:g} waves rms, at least {args.separation:g} px apart, "
          f"seed {args.seed} (medians over the kept beads)")
    print(table(rows, [("beads", "d"), ("taken", "s"), ("kept", "d"), ("error", ".4f"),
                       ("beyond", ".4f")]))


if __name__ == "__main__":
    main()
