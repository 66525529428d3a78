"""A defocus gradient across the field: its cost against the same field without it
(issue 45).

    python bench/bench_gradient.py [--generator ours pyotf psfmodels] [--seeds 20 21]
                                   [--span 0.3]

For scenes of ``bench_power.py``'s setting (1024 x 1024, 150 beads, moderate field
aberrations, the rest drawn from the family), rendered by one optics code (the project's
simulator, pyotf or psfmodels: ``bench/independent.py``), the field error of
``estimate_operator`` at the true radius (8 x 8 grid, aligned relative l2 error against
the true PSFs, ``simulation.metrics.grid_errors``) without and with a defocus gradient
spanning ``--span`` waves rms over the field (0.3: +-0.15 about the field's own; the
scene's draw otherwise identical). The issue's bound: the error with the gradient at
most 1.3x the error without.

The photons' share (``--oracle``, on by default): the same field error of a Poisson oracle
that knows every bead's true centre, true PSF, photons and background, and sees only the
camera's shot and read noise (each bead's patch drawn on its own, so no neighbour's light
either), through the estimator's own stages after the cut (the window, the PCA, the
thin-plate field and the cone: ``fit_patches``). What the oracle loses to the gradient
is what the photons cost at that window, for any estimator of this model; ``est/oracle``
is what the estimator adds to it.

The pixels' share (``pixels``): the image's own pixels (in photons) cut at the true
centres with the true background taken out, through the same stages: what the data
themselves hold (their sampling, the camera's quantisation, the neighbours' light) once
the centres and the background are known. ``est/pixels`` near 1 says the estimator's
centres and background cost nothing there.
"""

from __future__ import annotations

import argparse

import numpy as np

from bench_power import SETTING
from benchlib import optics_type, table
from napari_psfspace.core.beads.patches import Patches, extract_patches, patch_size
from napari_psfspace.core.beads.window import bump_window
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.model.patch_fit import fit_patches
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.scene_set import random_scene


def poisson_oracle(truth, r: int, seed: int) -> float:
    """The field error of the Poisson oracle (the module's docstring) at radius ``r``."""
    rng = np.random.default_rng([seed, 66])
    size = patch_size(r)
    win = bump_window(size, r, 1.2 * r)
    ys, xs = truth.positions[:, 0], truth.positions[:, 1]
    psfs = truth._psfs(ys, xs, size)
    bg = truth.background[np.round(ys).astype(int), np.round(xs).astype(int)].astype(float)
    expect = psfs * truth.amplitudes[:, None, None] + bg[:, None, None]
    noisy = rng.poisson(expect) + rng.normal(0.0, truth.read_noise, expect.shape)
    psf = (noisy - bg[:, None, None]) * win
    flux = psf.sum(axis=(1, 2))
    keep = flux > 0
    psf = psf[keep] / flux[keep, None, None]
    noise = np.sqrt(bg[keep] + truth.read_noise ** 2)
    p = Patches(truth.positions[keep], noisy[keep], np.broadcast_to(
        bg[keep, None, None], psf.shape).copy(), psf, flux[keep], noise, float(r), 1.2 * r)
    _, op, _, _ = fit_patches(p, truth.shape)
    return float(np.mean(grid_errors(op, truth, n=8)))


def pixels_oracle(image, truth, r: int) -> float:
    """The field error of the image's own pixels at the true centres, the true
    background taken out (the module's docstring), at radius ``r``."""
    photons = (np.asarray(image, np.float64) - truth.offset) / truth.gain
    cut = extract_patches(photons, truth.positions, r)
    bg = extract_patches(truth.background.astype(np.float64), truth.positions, r).raw
    win = bump_window(cut.size, r, cut.r_ext)
    psf = (cut.raw - bg) * win
    flux = psf.sum(axis=(1, 2))
    keep = flux > 0
    p = Patches(cut.centers[keep], cut.raw[keep], bg[keep],
                psf[keep] / flux[keep, None, None], flux[keep], cut.noise[keep], cut.r,
                cut.r_ext)
    _, op, _, _ = fit_patches(p, truth.shape)
    return float(np.mean(grid_errors(op, truth, n=8)))


def run(generator: str, seed: int, span: float, oracle: bool = True) -> dict:
    row = {"gen": generator, "seed": seed}
    for name, eff in (("without", None), ("with", {"defocus_gradient": span})):
        image, truth, _ = random_scene(seed, effects=eff, optics_type=optics_type(generator),
                                       **SETTING)
        try:
            op = estimate_operator(image, psf_radius=truth.psf_radius)
        except ValueError as exc:
            row["note"] = str(exc)[:60]
            return row
        row[name] = float(np.mean(grid_errors(op, truth, n=8)))
        row[f"{name}_beads"] = int(op.metadata["n_beads_used"])
        row[f"{name}_I"] = int(op.metadata["n_psf"])
        if oracle:
            row[f"{name}_oracle"] = poisson_oracle(truth, truth.psf_radius, seed)
            row[f"{name}_pixels"] = pixels_oracle(image, truth, truth.psf_radius)
    row["ratio"] = row["with"] / row["without"]
    if oracle:
        row["oracle_ratio"] = row["with_oracle"] / row["without_oracle"]
        row["est/oracle"] = row["with"] / row["with_oracle"]
        row["pixels_ratio"] = row["with_pixels"] / row["without_pixels"]
        row["est/pixels"] = row["with"] / row["with_pixels"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--generator", nargs="+", default=["ours", "pyotf", "psfmodels"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[20, 21, 22])
    ap.add_argument("--span", type=float, default=0.3)
    ap.add_argument("--no-oracle", dest="oracle", action="store_false",
                    help="skip the Poisson oracle's columns")
    args = ap.parse_args()
    rows = []
    for gen in args.generator:
        for seed in args.seeds:
            rows.append(run(gen, seed, args.span, args.oracle))
            print({k: (round(v, 4) if isinstance(v, float) else v)
                   for k, v in rows[-1].items()}, flush=True)
    print(f"\nField error without and with a defocus gradient of {args.span:g} waves rms "
          "across the field")
    cols = [("gen", "s"), ("seed", "d"), ("without", ".4f"), ("with", ".4f"), ("ratio", ".2f")]
    if args.oracle:
        cols += [("without_oracle", ".4f"), ("with_oracle", ".4f"), ("oracle_ratio", ".2f"),
                 ("est/oracle", ".2f"), ("pixels_ratio", ".2f"), ("est/pixels", ".2f")]
    print(table(rows, cols + [("without_beads", "d"), ("with_beads", "d"),
                              ("without_I", "d"), ("with_I", "d")]))
    summary = []
    for gen in args.generator:
        r = np.array([x["ratio"] for x in rows if x["gen"] == gen and "ratio" in x])
        if len(r):
            summary.append({"gen": gen, "n": len(r), "mean": r.mean(),
                            "se": r.std(ddof=1) / np.sqrt(len(r)) if len(r) > 1 else 0.0,
                            "worst": r.max(),
                            "ratio_of_means": np.mean([x["with"] for x in rows
                                                       if x["gen"] == gen and "ratio" in x])
                            / np.mean([x["without"] for x in rows
                                       if x["gen"] == gen and "ratio" in x])})
            if args.oracle:
                done = [x for x in rows if x["gen"] == gen and "ratio" in x]
                o = np.array([x["oracle_ratio"] for x in done])
                summary[-1].update(
                    oracle_mean=o.mean(), oracle_worst=o.max(),
                    over=int(np.sum(r > 1.3)), over_oracle_too=int(np.sum((r > 1.3) & (o > 1.3))),
                    over_pixels_too=int(sum(x["ratio"] > 1.3 and x["pixels_ratio"] > 1.3
                                            for x in done)),
                    worst_est_oracle=max(x["est/oracle"] for x in done),
                    worst_est_pixels=max(x["est/pixels"] for x in done))
    cols = [("gen", "s"), ("n", "d"), ("mean", ".3f"), ("se", ".3f"), ("worst", ".3f"),
            ("ratio_of_means", ".3f")]
    if args.oracle:
        cols += [("oracle_mean", ".3f"), ("oracle_worst", ".3f"), ("over", "d"),
                 ("over_oracle_too", "d"), ("over_pixels_too", "d"),
                 ("worst_est_oracle", ".2f"), ("worst_est_pixels", ".2f")]
    print(table(summary, cols))


if __name__ == "__main__":
    main()
