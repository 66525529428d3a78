"""Deblur 3D at the panel's defaults on a measured stack (SP8 confocal, 71 x 1024 x 1024).

The 3D step's defaults: the model learnt with the panel's radius (16 px) and every plane
(``z_radius`` None), then space-varying Richardson-Lucy for at most 50 iterations with
the library's stopping rule. Printed: the model's kernel, the setup's and each
iteration's seconds, the time estimate given before the iterations against the actual
time, and the stopping rule's result against 50 iterations' (relative l2), with the
relative change of each iteration and the distance of checkpoints to the 50th iterate.

    python bench/bench_deblur3d_panel.py --save /tmp/plain50.npy     # plain RL, 50
    python bench/bench_deblur3d_panel.py --accelerate --stop 0.005 \
        --reference /tmp/plain50.npy                                   # the panel's

Needs ``../shared/data/sp8_confocal_beads`` (``--file astig``: the astigmatic stack); the
model is learnt once and kept in the temp folder (``--fresh`` learns it again).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from benchlib import table

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FILES = {"sp8": DATA / "sp8_confocal_beads" / "sp8_series045_beads_zyx_uint8.tif",
         "astig": DATA / "astigmatic_beads" / "psfextractor_astigmatism_zyx_uint8.tif"}
#: Iterates kept to measure their distance to the last.
CHECKPOINTS = (5, 8, 10, 12, 15, 20, 25, 30, 40)


def _model(stack, voxel, radius: float, fresh: bool, name: str):
    from napari_psfspace.core.volume import estimate_operator_3d, load_operator_3d

    path = Path(tempfile.gettempdir()) / f"psfspace_panel_{name}_r{radius:g}.npz"
    if path.exists() and not fresh:
        return load_operator_3d(path), 0.0
    t0 = time.perf_counter()
    op = estimate_operator_3d(stack, psf_radius=radius, voxel_size=voxel)
    seconds = time.perf_counter() - t0
    op.save(path)
    return op, seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--radius", type=float, default=16.0)
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--file", choices=sorted(FILES), default="sp8")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--accelerate", action="store_true",
                    help="Biggs-Andrews acceleration (the panel's default)")
    ap.add_argument("--stop", type=float, default=None,
                    help="the stopping rule's threshold (the panel's: STOP_FIT)")
    ap.add_argument("--save", type=Path, help="save the result (.npy)")
    ap.add_argument("--reference", type=Path,
                    help="a saved result (.npy, e.g. plain RL's 50 iterations): each "
                         "checkpoint's and the result's distance to it")
    args = ap.parse_args()
    path = FILES[args.file]
    if not path.exists():
        raise SystemExit(f"needs {path} (../shared/data beside the repository)")
    from napari_psfspace.core.volume.deconvolve3d import iter_richardson_lucy_3d
    from napari_psfspace.io import read_stack

    stack, info = read_stack(str(path))
    voxel = ((info.z_spacing, info.pixel_size, info.pixel_size)
             if info.pixel_size and info.z_spacing else None)
    op, learn_s = _model(stack, voxel, args.radius, args.fresh, args.file)
    print(f"model: I = {op.n_psf}, kernel {op.kernel_shape}, plane {op.plane}, "
          f"voxel {voxel}, learnt in {learn_s:.0f} s", flush=True)
    gen = iter_richardson_lucy_3d(stack, op, n_iter=args.iterations, stop=args.stop,
                                  accelerate=args.accelerate)
    checkpoints: dict[int, np.ndarray] = {}
    ends: list[float] = []
    t0 = time.perf_counter()
    setup_end, last = t0, ""
    try:
        while True:
            p = next(gen)
            if p.stage == "iteration" and p.message.count("change"):
                ends.append(time.perf_counter())
                k = len(ends)
                if k in CHECKPOINTS:
                    checkpoints[k] = gen.gi_frame.f_locals["u"].copy()
            elif p.stage in ("setup", "estimate"):  # the setup ends at its last record
                setup_end = time.perf_counter()
                if p.message != last:
                    print(f"{setup_end - t0:6.1f} s  {p.stage}: {p.message}", flush=True)
                last = p.message
    except StopIteration as stop:
        res = stop.value
    total = time.perf_counter() - t0
    times = np.diff([setup_end, *ends])
    final = res.volume
    norm = float(np.linalg.norm(final))
    ref = None if args.reference is None else np.load(args.reference)
    checkpoints[res.iterations] = final
    rows = []
    for k, u in sorted(checkpoints.items()):
        row = {"iteration": k, "change": res.changes[k - 1],
               "to_final": float(np.linalg.norm(u - final)) / norm,
               "seconds": float(ends[k - 1] - t0)}
        if ref is not None:
            row["to_reference"] = float(np.linalg.norm(u - ref) / np.linalg.norm(ref))
        rows.append(row)
    cols = [("iteration", "d"), ("change", ".2e"), ("to_final", ".4f"), ("seconds", ".0f")]
    print(table(rows, cols + ([("to_reference", ".4f")] if ref is not None else [])))
    if args.save:
        np.save(args.save, final)
    dev = np.asarray(res.deviances)
    gains = (dev[:-1] - dev[1:]) / dev[1:]
    print("fit improvement of iterate k (k = 1..):",
          " ".join(f"{g:.1e}" for g in gains), flush=True)
    out = {"stack": "x".join(map(str, stack.shape)), "kernel": list(op.kernel_shape),
           "I": op.n_psf, "n_kernels": res.n_kernels, "setup_s": setup_end - t0,
           "per_iteration_s": float(np.median(times)), "total_s": total,
           "estimate_s": res.estimate_s, "iterations": res.iterations,
           "stopped": res.stopped, "accelerate": args.accelerate, "stop": args.stop,
           "changes": res.changes, "deviances": res.deviances, "checkpoints": rows}
    print(json.dumps({k: v for k, v in out.items()
                      if k not in ("changes", "deviances", "checkpoints")}, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
