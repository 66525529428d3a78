"""Where a crowded field's error enters: the neighbours' light of the deblend drawn by
the truth instead of the model.

    python bench/bench_neighbour_oracle.py [--seeds 0 1] [--beads 300 600]
                                           [--gradient 0.15] [--separation 30]

The noise-free scenes of ``bench_more_beads.py`` (``bench_estimator_ladder.py``'s field
with a defocus gradient of ``+-gradient`` waves rms, beads at least ``--separation`` px
apart). In a crowded field the estimate takes each kept bead's neighbours' light out of
its patch with a model learnt from the patches (``core.model.deblend``). Each column
replaces that light, for every detection matched to a true bead within 3 px:

- ``model``: the estimate as it is;
- ``true_window``: the true PSF at the matched bead's true position, windowed as the
  model's PSFs are (the bump window to ``1.2 r``), times the true photons in that window:
  the model's shape inside the window made exact;
- ``true_full``: the whole true PSF (to ``3 r``, as the scene is rendered), times the true
  photons: the tails beyond the window too.

The bead itself is never its own neighbour (the model's rule: the detection at its own
centre is skipped), so its light stays in its patch. Error: the mean over an 8 x 8 grid
of the aligned relative l2 error against the true PSFs.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from bench_estimator_ladder import scene
from benchlib import table
from napari_psfspace.core.beads.detect import STRUCTURE
from napari_psfspace.core.beads.patches import patch_size
from napari_psfspace.core.beads.window import bump_window
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model import deblend
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.scene import RENDER_RADIUS_FACTOR

MODES = ("model", "true_window", "true_full")


class TruePsfs:
    """The ``psf_at``/``psf_size`` of a model, drawn by the truth: at a detection, the
    true PSF of the nearest true bead, moved to its true position (cubic shift)."""

    def __init__(self, truth, size: int, window: np.ndarray | None):
        self.truth, self.psf_size, self.window = truth, size, window
        self.tree = cKDTree(truth.positions)

    def psf_at(self, y: float, x: float) -> np.ndarray:
        k = int(self.tree.query([y, x])[1])
        t = self.truth.positions[k]
        h = self.truth.psf_at(*t, self.psf_size)
        if self.window is not None:
            h = h * self.window
            h = h / h.sum()
        return ndi.shift(h, t - np.array([y, x]), order=3, mode="constant")


def true_light(truth, mode: str):
    """A stand-in for ``deblend.model_light``: the detections' light as the truth's."""
    r = truth.psf_radius
    full = 2 * RENDER_RADIUS_FACTOR * r + 1
    size = full if mode == "true_full" else patch_size(r)
    window = None if mode == "true_full" else bump_window(size, r, 1.2 * r)
    psfs = TruePsfs(truth, size, window)

    def model_light(patches, image, beads, psf_radius, light=None):
        pos = beads.positions[beads.status != STRUCTURE]
        dist, idx = psfs.tree.query(pos)
        flux = np.zeros(len(pos))
        c, h = full // 2, size // 2
        for j in np.flatnonzero(dist <= 3.0):
            whole = truth.psf_at(*truth.positions[idx[j]], full)  # sum 1 as rendered
            inner = whole[c - h:c + h + 1, c - h:c + h + 1]
            share = (inner * window).sum() if window is not None else inner.sum()
            flux[j] = truth.amplitudes[idx[j]] * share
        return deblend.ModelLight(psfs, pos, flux)

    return model_light


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--beads", type=int, nargs="+", default=[300, 600])
    ap.add_argument("--gradient", type=float, default=0.15)
    ap.add_argument("--separation", type=float, default=30.0)
    args = ap.parse_args()
    shipped = deblend.model_light
    rows = []
    for n in args.beads:
        for seed in args.seeds:
            image, truth = scene(seed, args.gradient, False, n, args.separation)
            row = {"seed": seed, "beads": n}
            for mode in MODES:
                deblend.model_light = shipped if mode == "model" else true_light(truth, mode)
                try:
                    est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius))
                finally:
                    deblend.model_light = shipped
                row[mode] = float(grid_errors(est.operator, truth, 8).mean())
            rows.append(row)
            print(rows[-1], flush=True)
    print(f"\nThe neighbours' light drawn by the truth, noise-free, gradient "
          f"+-{args.gradient:g} waves rms, at least {args.separation:g} px apart")
    print(table(rows, [("seed", "d"), ("beads", "d")] + [(m, ".4f") for m in MODES]))


if __name__ == "__main__":
    main()
