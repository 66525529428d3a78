"""The main job on an embedded default: simulate a wide field, estimate, report, draw.

``psfspace demo`` runs :func:`run_demo`. Everything it writes goes into one folder:

==========================  ==========================================================
``image.tif``               the simulated bead image (uint16, pixel size in the tags)
``model.npz``               the estimated operator (see docs/file-format.md)
``psf_grid_true.tif``       true PSFs on an 8 x 8 grid spanning the field (64, P, P)
``psf_grid_estimated.tif``  estimated PSFs at the same positions (64, P, P)
``psf_grid.png``            true (left) and estimated (right) PSF grids, each tile
                            scaled to its own maximum, gamma 0.5
``basis.png``               the learnt PSF basis h_i
``coefficient_maps.png``    the coefficient maps alpha_i over the field
``errors.json``             the error table below, with the parameters
==========================  ==========================================================
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .core.common.atomic import write_set
from .core.common.mosaic import mosaic
from .core.common.progress import Progress, run_with_progress
from .core.diagnosis.loop import iter_heldout_error
from .core.diagnosis.metric import line as heldout_line
from .core.model.estimate import iter_estimate
from .core.simulation import simulate_beads
from .core.simulation.metrics import evaluate_against_truth, grid_positions
from .figure import figure_png
from .io import write_tiff

#: Embedded default scenes: (shape, number of beads, aberration preset).
SCENES = {
    "wide": ((2048, 2048), 400, "strong"),
    "moderate": ((1024, 1024), 150, "moderate"),
    "small": ((512, 512), 50, "moderate"),
}


def run_demo(out_dir: str | os.PathLike = "demo-output", *, scene: str = "wide", seed: int = 0,
             progress: Callable[[Progress], None] | None = None) -> dict:
    """Simulate a bead image, estimate its operator, compare with the truth, write figures.

    Parameters
    ----------
    out_dir : path-like
        Folder for the outputs (created if needed).
    scene : {"wide", "moderate", "small"}
        Embedded default scene (see :data:`SCENES`).
    seed : int
        Seed of the simulation.
    progress : callable, optional
        Receives :class:`Progress` records.

    Returns
    -------
    dict
        The error table and run information (also written to ``errors.json``).
    """
    if scene not in SCENES:
        raise ValueError(f"`scene` must be one of {sorted(SCENES)}, got {scene!r}.")
    shape, n_beads, preset = SCENES[scene]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = progress or (lambda p: None)

    t0 = time.perf_counter()
    image, truth = simulate_beads(shape, n_beads, aberrations=preset, seed=seed)
    t_sim = time.perf_counter() - t0
    report(Progress("simulate", 0.0, f"{shape[0]}x{shape[1]} image, {n_beads} beads, "
                    f"{preset} aberrations, PSF radius {truth.psf_radius} px"))
    pixel = truth.optics.pixel_size

    t0 = time.perf_counter()
    est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius), report)
    t_est = time.perf_counter() - t0
    # the one accuracy figure every report gives (core/diagnosis/metric.py)
    held = run_with_progress(iter_heldout_error(image, psf_radius=truth.psf_radius), report)
    op = est.operator

    errors = evaluate_against_truth(op, truth, 8)
    # the figures span the field edge to edge (half a patch from the border)
    ys, xs = grid_positions(shape, 8, layout="edges", margin=op.psf_size // 2)
    true = np.array([[truth.psf_at(y, x, op.psf_size) for x in xs] for y in ys])
    estim = np.array([[op.psf_at(y, x) for x in xs] for y in ys])
    left = mosaic(true, gap=2, gamma=0.5)
    right = mosaic(estim.clip(0, None), gap=2, gamma=0.5)
    sep = np.full((left.shape[0], 12), np.nan)
    px = truth.optics.pixel_size
    tile = f"{op.psf_size * px:.2f} µm" if px else f"{op.psf_size} px"
    pngs = {"psf_grid.png": figure_png(
        np.hstack([left, sep, right]), title="PSF over the field: true (left), estimated "
        "(right)", unit="relative", limits=(0.0, 1.0), cmap="magma", size=900,
        note=f"8 x 8 field positions, tiles {tile}, each scaled to its peak, gamma 0.5")}
    pngs["basis.png"] = figure_png(
        mosaic(op.basis, gap=2, normalize="each", fill=np.nan),
        title=f"PSF basis h_0..h_{op.n_psf - 1}", unit="relative", limits=(-1.0, 1.0),
        cmap="diverging", note="each scaled to its largest magnitude, left to right, row by row")
    maps = op.coefficient_maps()[:, ::8, ::8]
    field = f"{shape[1] * px:.0f} µm" if px else f"{shape[1]} px"
    pngs["coefficient_maps.png"] = figure_png(
        mosaic(maps, gap=4, normalize="each", fill=np.nan),
        title=f"Coefficient maps alpha_0..alpha_{op.n_psf - 1}", unit="relative",
        limits=(-1.0, 1.0), cmap="diverging",
        note=f"each over the {field} field, scaled to its largest magnitude")

    result = {
        "scene": scene,
        "shape": list(shape),
        "n_beads_simulated": n_beads,
        "aberrations": preset,
        "seed": seed,
        "psf_radius": truth.psf_radius,
        "n_psf": op.n_psf,
        "n_beads_used": op.metadata["n_beads_used"],
        "heldout_error": held.to_dict(),
        "seconds_simulate": round(t_sim, 2),
        "seconds_estimate": round(t_est, 2),
        "errors": errors,
    }
    size = op.psf_size
    tiffs = {"image.tif": (image, pixel), "psf_grid_true.tif": (true.reshape(64, size, size),
                                                                None),
             "psf_grid_estimated.tif": (estim.reshape(64, size, size), None)}
    text = json.dumps(result, indent=2).encode("utf-8")
    # one set, errors.json (the summary) last in: never one run's figures beside another's
    write_set([(out / "errors.json", lambda fh: fh.write(text)),
               (out / "model.npz", lambda fh: op.save(out / "model.npz", into=fh))]
              + [(out / n, _tiff_writer(out / n, a, p)) for n, (a, p) in tiffs.items()]
              + [(out / n, _bytes_writer(b)) for n, b in pngs.items()])
    return result


def _tiff_writer(path, data, pixel):
    return lambda fh: write_tiff(path, data, pixel_size=pixel, into=fh)


def _bytes_writer(data: bytes):
    return lambda fh: fh.write(data)


def format_table(result: dict) -> str:
    """The demo's error table as plain text."""
    e = result["errors"]
    lines = [
        f"Scene {result['scene']}: {result['shape'][0]}x{result['shape'][1]}, "
        f"{result['n_beads_simulated']} beads, {result['aberrations']} aberrations; "
        f"basis I = {result['n_psf']} from {result['n_beads_used']} beads; "
        f"estimated in {result['seconds_estimate']:.1f} s",
        "",
        "PSF error at 8x8 positions (cell centres)     mean     max",
        "  (rescaled relative l2, ||c*est - true|| / ||true||)",
        f"  estimate, best sub-pixel alignment         {e['aligned']['mean']:.4f}  "
        f"{e['aligned']['max']:.4f}",
        f"  estimate, unaligned                        {e['unaligned']['mean']:.4f}  "
        f"{e['unaligned']['max']:.4f}",
        f"  best single shift-invariant PSF (aligned)  {e['shift_invariant']['mean']:.4f}  "
        f"{e['shift_invariant']['max']:.4f}",
        f"  ratio estimate / shift-invariant           {e['ratio']:.3f}",
        f"  estimate, grid reaching the field's edge   {e['edges']['mean']:.4f}  "
        f"{e['edges']['max']:.4f}",
    ]
    h = result.get("heldout_error")
    if h:
        lines += ["", heldout_line(h["error"], h["noise_floor"], h["n_beads"])]
    return "\n".join(lines)
