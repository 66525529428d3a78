"""The longest wait for Cancel: the seconds between two progress records of the 3D
step's generators on the measured SP8 confocal stack (71 x 1024 x 1024) at the panel's
defaults (Cancel is honoured at the next record).

    python bench/bench_cancel_gaps.py [--iterations 3]

Needs ``../shared/data/sp8_confocal_beads``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from _common import table

SP8 = (Path(__file__).resolve().parents[2] / "shared" / "data" / "sp8_confocal_beads"
       / "sp8_series045_beads_zyx_uint8.tif")


def gaps(gen) -> tuple[list[dict], object]:
    """(rows of the longest gap per stage, the generator's value)."""
    longest: dict[str, float] = {}
    t = time.perf_counter()
    while True:
        try:
            rec = next(gen)
        except StopIteration as stop:
            value = stop.value
            break
        now = time.perf_counter()
        longest[rec.stage] = max(longest.get(rec.stage, 0.0), now - t)
        t = now
    return [{"stage": k, "longest_s": v} for k, v in longest.items()], value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--radius", type=float, default=16.0)
    args = ap.parse_args()
    if not SP8.exists():
        raise SystemExit(f"needs {SP8}")
    from napari_psfspace.core.volume import iter_estimate_operator_3d
    from napari_psfspace.core.volume.deconvolve3d import iter_richardson_lucy_3d
    from napari_psfspace.io import read_stack

    stack, info = read_stack(str(SP8))
    voxel = (info.z_spacing, info.pixel_size, info.pixel_size)
    rows, est = gaps(iter_estimate_operator_3d(stack, psf_radius=args.radius,
                                               voxel_size=voxel))
    for r in rows:
        r["step"] = "Learn 3D PSF"
    more, _ = gaps(iter_richardson_lucy_3d(stack, est.operator, n_iter=args.iterations,
                                           accelerate=True))
    for r in more:
        r["step"] = "Deblur 3D"
    print(table(rows + more, [("step", "s"), ("stage", "s"), ("longest_s", ".2f")]))


if __name__ == "__main__":
    main()
