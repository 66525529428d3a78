"""Where the estimator's error enters: an oracle per stage, on a clean field and on a
defocus gradient, noise-free and with the camera's noise.

    python bench/bench_estimator_ladder.py [--seeds 0 1 2] [--gradient 0.15] [--noise]
                                           [--beads 150] [--photons 1 10 100]

The scene is ``bench_accuracy.py``'s moderate one (1024 x 1024, 150 beads, NA 1.3), with
and without defocus (Noll 4) growing linearly along the columns, ``+-gradient`` waves rms
at the field's left and right edges. "Noise-free" renders the beads' expected photons on a
constant background of 100 photons (no shot noise, no camera); ``--noise`` takes the
simulator's camera image. Each row replaces one stage of the estimate with its oracle:

- the full estimate;
- the same with every bead kept (no outlier rejection);
- patches cut at the true bead centres (spline re-sampling), then by a Fourier phase ramp
  (``core.beads.subpixel``);
- the paper's background (order-2 polynomial on the patch beyond ``r``) in place of the
  plane on a ring;
- the background known (the constant that was added), at the true centres;
- the true PSFs themselves at the true centres, windowed: what the window, the PCA, the
  thin-plate field and the cone leave.

Error: the mean over an 8 x 8 grid of the aligned relative l2 error against the true PSFs
(``simulation.metrics.grid_errors``), and the same over the grid's outer ring ("rim").
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial import cKDTree

from benchlib import table
from napari_psfspace.core.beads import patches as patch_module
from napari_psfspace.core.beads.detect import STRUCTURE
from napari_psfspace.core.beads.overlap import neighbour_light
from napari_psfspace.core.beads.patches import Patches, extract_patches
from napari_psfspace.core.beads.subpixel import fourier_resample_patches
from napari_psfspace.core.beads.window import bump_window
from napari_psfspace.core.common.validate import as_image
from napari_psfspace.core.model import estimate
from napari_psfspace.core.model.estimate import centre_beads, find_usable_beads, usable_patches
from napari_psfspace.core.model.patch_fit import fit_patches
from napari_psfspace.core.simulation import simulate_beads
from napari_psfspace.core.simulation.aberrations import FieldAberrations, as_aberrations
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.render import render_beads
from napari_psfspace.core.simulation.scene import RENDER_RADIUS_FACTOR

BACKGROUND = 100.0  # photons, the noise-free scenes' constant background


def aberrations(gradient: float) -> FieldAberrations:
    """The moderate preset with defocus growing along the columns (``u`` in [-1, 1])."""
    terms = {j: list(v) for j, v in as_aberrations("moderate").terms.items()}
    z4 = terms.get(4, [0.0] * 6)
    z4[1] += gradient
    terms[4] = z4
    return FieldAberrations(terms)


def scene(seed: int, gradient: float, noise: bool, n_beads: int = 150,
          separation: float | None = None, photons: float = 1.0):
    """The image (noise-free: float photons) and the simulator's truth; ``photons``
    scales the beads' photons (2e4 to 6e4 each); above 1 the image is float, not 16 bits."""
    image, truth = simulate_beads((1024, 1024), n_beads, aberrations=aberrations(gradient),
                                  seed=seed, min_separation=separation,
                                  amplitude=(2e4 * photons, 6e4 * photons),
                                  dtype=np.uint16 if photons <= 1 else np.float32)
    if noise:
        return image, truth
    photons = np.full(image.shape, BACKGROUND)
    render_beads(photons, truth.positions, truth.amplitudes, truth.aberrations, truth.optics,
                 RENDER_RADIUS_FACTOR * truth.psf_radius)
    return photons, truth


def cut(image, centres, r, **kw) -> Patches:
    """:func:`extract_patches`, less any patch with no light left (a crowded field)."""
    p = extract_patches(image, centres, r, **kw)
    return p.subset(p.flux > 0)


def errors(patches: Patches, shape, truth, **kw) -> tuple[float, float, int, int]:
    basis, op, _, _ = fit_patches(patches, shape, **kw)
    e = grid_errors(op, truth, 8)
    rim = np.r_[e[0], e[-1], e[1:-1, 0], e[1:-1, -1]]
    return float(e.mean()), float(rim.mean()), basis.n_psf, int(basis.inliers.sum())


def ladder(seed: int, gradient: float, noise: bool, n_beads: int,
           separation: float | None = None, photons: float = 1.0) -> dict:
    image, truth = scene(seed, gradient, noise, n_beads, separation, photons)
    r = truth.psf_radius
    raw = np.asarray(image)
    beads, img = find_usable_beads(raw, as_image(raw), r, beads=None, threshold=8.0,
                                   saturation=None)
    kept = centre_beads(img, beads, r)
    kept, ours, _ = usable_patches(img, beads, kept, r)
    dist, nearest = cKDTree(truth.positions).query(ours.centers)
    # the oracles: the beads found within half a PSF radius (a defocused bead's Gaussian
    # centre lies up to a few pixels from its chief ray), at their true centres
    found = dist < 0.5 * r
    true_pos = truth.positions[nearest[found]]
    moved = beads.positions.copy()  # the neighbour model with each bead at its true centre
    moved[kept[found]] = true_pos
    light = (neighbour_light(img, moved[beads.status != STRUCTURE], r)
             if estimate.SUBTRACT_NEIGHBOURS else None)
    shape = img.shape
    rows = {"full estimate": errors(ours, shape, truth),
            "all beads kept": errors(ours, shape, truth, z_threshold=np.inf)}
    at_truth = cut(img, true_pos, r, neighbours=light)
    true_pos = at_truth.centers
    rows["true centres"] = errors(at_truth, shape, truth)
    spline = patch_module.resample_patches
    patch_module.resample_patches = fourier_resample_patches
    try:
        fourier = cut(img, true_pos, r, neighbours=light)
    finally:
        patch_module.resample_patches = spline
    rows["true centres, Fourier shift"] = errors(fourier, shape, truth)
    rows["true centres, paper's background"] = errors(
        cut(img, true_pos, r, background="patch", neighbours=light), shape, truth)
    win = bump_window(at_truth.size, r, at_truth.r_ext)
    if not noise:
        known = (at_truth.raw - BACKGROUND) * win
        known /= known.sum(axis=(1, 2), keepdims=True)
        rows["true centres, background known"] = errors(
            Patches(true_pos, at_truth.raw, np.full_like(known, BACKGROUND), known,
                    at_truth.flux, np.full(len(known), 1e-6), r, at_truth.r_ext),
            shape, truth, denoise=False)
    psfs = np.array([truth.psf_at(y, x, at_truth.size) for y, x in true_pos]) * win
    psfs /= psfs.sum(axis=(1, 2), keepdims=True)
    rows["true PSFs, windowed"] = errors(
        Patches(true_pos, psfs, np.zeros_like(psfs), psfs, np.ones(len(psfs)),
                np.full(len(psfs), 1e-6), r, at_truth.r_ext), shape, truth, denoise=False)
    return rows


def photons_sweep(seeds, gradient: float, factors) -> None:
    """The full estimate with the camera's noise at ``factors`` times the photons: the
    gradient's cost against the clean field's, and each bead's noise floor (the norm of
    its windowed noise over its patch's), whose ratio between the fields is what the
    photons alone make of it."""
    from napari_psfspace.core.common.progress import run_with_progress
    from napari_psfspace.core.model.estimate import iter_estimate
    from napari_psfspace.core.model.heldout import noise_floors

    rows = []
    for f in factors:
        row = {"photons": f"x{f:g}"}
        for g, name in ((0.0, "clean"), (gradient, "gradient")):
            err, floor = [], []
            for seed in seeds:
                image, truth = scene(seed, g, True, photons=f)
                est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius))
                err.append(float(grid_errors(est.operator, truth, 8).mean()))
                floor.append(float(np.median(noise_floors(est.patches))))
            row[name], row[f"{name}_floor"] = np.mean(err), np.mean(floor)
        row["ratio"] = row["gradient"] / row["clean"]
        row["floor_ratio"] = row["gradient_floor"] / row["clean_floor"]
        rows.append(row)
        print(rows[-1], flush=True)
    print(f"\nThe gradient's cost with the camera's noise at more photons (float images above x1), "
          f"seeds {list(seeds)} (means); floor: the beads' median noise floor")
    print(table(rows, [("photons", "s"), ("clean", ".4f"), ("gradient", ".4f"),
                       ("ratio", ".2f"), ("clean_floor", ".4f"), ("gradient_floor", ".4f"),
                       ("floor_ratio", ".2f")]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--gradient", type=float, default=0.15)
    ap.add_argument("--beads", type=int, default=150)
    ap.add_argument("--noise", action="store_true")
    ap.add_argument("--photons", type=float, nargs="+", default=None,
                    help="instead of the ladder: the full estimate with noise at these "
                         "multiples of the photons")
    args = ap.parse_args()
    if args.photons:
        photons_sweep(args.seeds, args.gradient, args.photons)
        return
    out = []
    runs = {g: [ladder(s, g, args.noise, args.beads) for s in args.seeds]
            for g in (0.0, args.gradient)}
    for step in runs[0.0][0]:
        row = {"step": step}
        for g, name in ((0.0, "clean"), (args.gradient, "gradient")):
            v = np.array([r[step] for r in runs[g]])
            row[name] = v[:, 0].mean()
            row[f"{name}_rim"] = v[:, 1].mean()
            row[f"{name}_I"] = f"{v[:, 2].min():.0f}-{v[:, 2].max():.0f}"
            row[f"{name}_beads"] = f"{v[:, 3].min():.0f}-{v[:, 3].max():.0f}"
        out.append(row)
    print(f"Oracle ladder, {'camera noise' if args.noise else 'noise-free'}, "
          f"{args.beads} beads, gradient +-{args.gradient:g} waves rms, seeds {args.seeds} "
          "(means)")
    cols = [("step", "s")]
    for name in ("clean", "gradient"):
        cols += [(name, ".4f"), (f"{name}_rim", ".4f"), (f"{name}_I", "s"),
                 (f"{name}_beads", "s")]
    print(table(out, cols))


if __name__ == "__main__":
    main()
