"""More beads of one field: does the estimate's error fall, as the oracle's does?

    python bench/bench_more_beads.py [--seeds 0 1 2] [--beads 150 300 600]
                                     [--separation 30] [--noise]

The scenes of ``bench_estimator_ladder.py`` (1024 x 1024, moderate aberrations, NA 1.3,
with and without a defocus gradient of +-0.15 waves rms), with 150, 300 and 600 beads at
least ``--separation`` pixels apart (30: one and a half times the gradient field's PSF
radius; 600 beads do not fit at the simulator's default of two and a half radii).
Noise-free unless ``--noise``. Columns: the full estimate's mean error over an 8 x 8
grid (aligned relative l2 against the true PSFs), its basis size and beads used, and
the oracle: the true PSFs at the true centres through the same PCA, thin-plate field and
cone.
"""

from __future__ import annotations

import argparse

import numpy as np

from bench_estimator_ladder import scene
from benchlib import table
from napari_psfspace.core.beads.patches import Patches, patch_size
from napari_psfspace.core.beads.window import bump_window
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.model.patch_fit import fit_patches
from napari_psfspace.core.simulation.metrics import grid_errors


def oracle(truth) -> float:
    r = truth.psf_radius
    size = patch_size(r)
    win = bump_window(size, r, 1.2 * r)
    psfs = np.array([truth.psf_at(y, x, size) for y, x in truth.positions]) * win
    psfs /= psfs.sum(axis=(1, 2), keepdims=True)
    p = Patches(truth.positions, psfs, np.zeros_like(psfs), psfs, np.ones(len(psfs)),
                np.full(len(psfs), 1e-6), r, 1.2 * r)
    _, op, _, _ = fit_patches(p, truth.shape, denoise=False)
    return float(grid_errors(op, truth, 8).mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--beads", type=int, nargs="+", default=[150, 300, 600])
    ap.add_argument("--separation", type=float, default=30.0)
    ap.add_argument("--gradient", type=float, default=0.15)
    ap.add_argument("--noise", action="store_true")
    args = ap.parse_args()
    rows = []
    for g in (0.0, args.gradient):
        for n in args.beads:
            err, orc, size, used = [], [], [], []
            for seed in args.seeds:
                image, truth = scene(seed, g, args.noise, n, args.separation)
                est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius))
                err.append(float(grid_errors(est.operator, truth, 8).mean()))
                orc.append(oracle(truth))
                size.append(est.operator.n_psf)
                used.append(est.operator.metadata["n_beads_used"])
            rows.append({"field": "gradient" if g else "clean", "beads": n,
                         "error": np.mean(err), "worst": np.max(err),
                         "I": f"{min(size)}-{max(size)}", "used": f"{min(used)}-{max(used)}",
                         "oracle": np.mean(orc)})
            print(rows[-1], flush=True)
    print(f"\nMore beads of one field, {'camera noise' if args.noise else 'noise-free'}, "
          f"at least {args.separation:g} px apart, seeds {args.seeds} (means)")
    print(table(rows, [("field", "s"), ("beads", "d"), ("error", ".4f"), ("worst", ".4f"),
                       ("I", "s"), ("used", "s"), ("oracle", ".4f")]))


if __name__ == "__main__":
    main()
