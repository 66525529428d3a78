"""The longest wait for Cancel in each step of the panel: the seconds between two
progress records of the step's core generator, driven as the panel drives it (a panel's
Cancel is honoured at the next record), on the measured images at their full size.

* ``--steps 2d``: Beads (radius suggestion, detection), Review, Model (estimate and
  held-out error), Diagnose, Deblur, on the best-focus slice of the SP8 confocal stack
  (1024 x 1024) and on the star field (2048 x 3072); Family on 10 slices of the SP8 stack.
* ``--steps 3d``: Learn 3D PSF and Deblur 3D on the SP8 stack (71 x 1024 x 1024) at the
  panel's defaults.

    python bench/bench_cancel_gaps.py [--steps 2d|3d|all] [--iterations 3]

Needs ``../shared/data/sp8_confocal_beads`` (and ``starfield_2d`` for its rows).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchlib import table

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SP8 = DATA / "sp8_confocal_beads" / "sp8_series045_beads_zyx_uint8.tif"
STARS = DATA / "starfield_2d" / "dash_starfield_uint16.tif"


def gaps(gen) -> tuple[list[dict], object]:
    """(rows of the longest waits per stage, the generator's value).

    ``gen`` is driven as the panel drives it, through
    :func:`~napari_psfspace.core.common.progress.responsive`: ``panel_s`` is the longest
    time between two records the panel receives (Cancel is honoured at the next one),
    ``core_s`` the longest between two of the core's own records (what Cancel would wait
    without the door). Each first wait runs from the generator's creation."""
    from napari_psfspace.core.common.progress import responsive

    count = [0]

    def counted(inner):
        while True:
            try:
                rec = next(inner)
            except StopIteration as stop:
                return stop.value
            count[0] += 1
            yield rec

    panel: dict[str, float] = {}
    core: dict[str, float] = {}
    driven = responsive(counted(gen))
    t = t_core = time.perf_counter()
    seen = 0
    while True:
        try:
            rec = next(driven)
        except StopIteration as stop:
            value = stop.value
            break
        now = time.perf_counter()
        panel[rec.stage] = max(panel.get(rec.stage, 0.0), now - t)
        t = now
        if count[0] != seen:  # one of the core's own records
            seen = count[0]
            core[rec.stage] = max(core.get(rec.stage, 0.0), now - t_core)
            t_core = now
    return [{"stage": k, "panel_s": panel[k], "core_s": core.get(k)} for k in panel], value


def labelled(rows: list[dict], image: str, step: str) -> list[dict]:
    for r in rows:
        r.update(image=image, step=step)
    return rows


def steps_2d(plane: np.ndarray, image: str) -> list[dict]:
    """Every 2-D step's gaps on one plane."""
    from napari_psfspace.core.beads.steps import iter_detect_beads, iter_suggest_psf_radius
    from napari_psfspace.core.diagnosis.loop import iter_diagnose, iter_heldout_error
    from napari_psfspace.core.model.estimate import iter_estimate
    from napari_psfspace.core.model.review import iter_patch_review
    from napari_psfspace.core.restore.deconvolve import iter_deblur

    out = []
    rows, r = gaps(iter_suggest_psf_radius(plane))
    out += labelled(rows, image, f"Beads (suggest: {r:.1f} px)")
    rows, beads = gaps(iter_detect_beads(plane, r))
    out += labelled(rows, image, "Beads (detect)")
    rows, _ = gaps(iter_patch_review(plane, beads, r))
    out += labelled(rows, image, "Review")
    rows, est = gaps(iter_estimate(plane, psf_radius=r))
    out += labelled(rows, image, "Model (estimate)")
    rows, _ = gaps(iter_heldout_error(plane, psf_radius=r))
    out += labelled(rows, image, "Model (held-out error)")
    rows, _ = gaps(iter_diagnose(plane, psf_radius=r))
    out += labelled(rows, image, "Diagnose")
    rows, _ = gaps(iter_deblur(plane, est.operator))
    out += labelled(rows, image, "Deblur")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", choices=("2d", "3d", "all"), default="all")
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--radius", type=float, default=16.0, help="Learn 3D's radius, px")
    args = ap.parse_args()
    if not SP8.exists():
        raise SystemExit(f"needs {SP8}")
    from napari_psfspace.core.beads.focus import best_focus_index
    from napari_psfspace.io import read_image, read_stack

    stack, info = read_stack(str(SP8))
    rows: list[dict] = []
    if args.steps in ("2d", "all"):
        focus = best_focus_index(stack)
        rows += steps_2d(stack[focus].astype(np.float32), f"SP8 slice {focus}")
        from napari_psfspace.core.family.estimate import iter_estimate_family
        part, _ = gaps(iter_estimate_family(
            [stack[k] for k in range(focus - 10, focus + 10, 2)], psf_radius=16.0))
        rows += labelled(part, "SP8, 10 slices", "Family")
        if STARS.exists():
            stars = read_image(str(STARS))[0].astype(np.float32)
            rows += steps_2d(stars, "star field")
    if args.steps in ("3d", "all"):
        from napari_psfspace.core.volume import iter_estimate_operator_3d
        from napari_psfspace.core.volume.deconvolve3d import iter_richardson_lucy_3d

        voxel = (info.z_spacing, info.pixel_size, info.pixel_size)
        part, est = gaps(iter_estimate_operator_3d(stack, psf_radius=args.radius,
                                                   voxel_size=voxel))
        rows += labelled(part, "SP8 stack", "Learn 3D PSF")
        part, _ = gaps(iter_richardson_lucy_3d(stack, est.operator, n_iter=args.iterations,
                                               accelerate=True, stop=True))
        rows += labelled(part, "SP8 stack", "Deblur 3D")
    print(table(rows, [("image", "s"), ("step", "s"), ("stage", "s"), ("panel_s", ".2f"),
                       ("core_s", ".2f")]))
    for key, what in (("panel_s", "through the panel's door"),
                      ("core_s", "between the core's own records")):
        worst = max(rows, key=lambda r: r[key] or 0.0)
        print(f"longest wait {what}: {worst[key]:.2f} s ({worst['image']}, "
              f"{worst['step']}, {worst['stage']})")


if __name__ == "__main__":
    main()
