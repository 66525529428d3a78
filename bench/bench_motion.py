"""Motion blur over the scene set: false alarms on effect-free scenes, and the power
to find a smear of each length (random direction), with the length and direction found.

    python bench/bench_motion.py [--scenes N] [--quick]
    python bench/bench_motion.py --astigmatism    # still beads at an astigmatic line focus
    python bench/bench_motion.py --measured       # every 4th slice of ../shared/data stacks

Scenes from :func:`~napari_psfspace.core.simulation.scene_set.random_scene` (512 x 512; pixel size
43-160 nm, NA 0.7-1.49, emission 450-700 nm, aberration presets and random fields,
20-600 beads, brightness spread, background 1-500 photons, 8/12/16-bit cameras). A
smear of ``L`` px can be seen only where its first spectral zero ``1 / L`` lies inside
the band where the beads' signal stands above the noise (``in_band``: ``L >=
min_visible_px``), and only where the spectrum on both sides of that zero stands clear of
the noise can a zero be told from noise: ``visible`` counts the scenes where the zero
lies inside the optics' cutoff ``2 NA / wavelength`` and the test, probed at the true
smear (``detect_motion(probe=...)``), finds both flanks of its zero line clear (its own
condition, at the true place). The power is given over those and over all.

``--removal``: the field error of the operator learnt with ``remove_motion=True``
against the still optics (``grid_errors``, 6 x 6), beside the operator that keeps the
smear and the one learnt from the same scene without it (the floor), on the scenes where
the smear was found.

``--astigmatism``: still beads (640 x 640, 70 beads, NA 1.3, 600 nm; 65, 100 and 130 nm
pixels) with a uniform astigmatism of 0.05-0.3 waves rms along a varying axis and 0.5-1.5
times as much defocus, near the line focus of an astigmatic lens: in geometric optics a
line focus is a uniform segment, which one image cannot tell from a smear. The table
gives, for each astigmatism and defocus, in how many scenes a line was read.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchlib import table
from napari_psfspace.core.beads.window import bump_window
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.model.motion import detect_motion
from napari_psfspace.core.simulation import FieldAberrations, Optics, simulate_beads
from napari_psfspace.core.simulation.scene_set import random_scene


def motion_of(image, truth, probe=None):
    """The motion test on the scene's patches; ``probe=(length, angle)``: the true smear,
    whose zero's flanks the record then says are clear of the noise or not."""
    est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius, holdout=None,
                                          n_psf=1))
    p = est.patches
    return detect_motion(p.psf, p.noise / p.flux, bump_window(p.size, p.r, p.r_ext),
                         positions=p.centers, probe=probe)


def visible(m, truth, length) -> bool:
    """The smear can be seen at all: its first zero ``1/L`` lies inside the optics'
    cutoff ``2 NA / wavelength`` (beyond it the optics pass nothing, and no test can
    find a zero there), and the test, probed at the true smear, finds both flanks of
    that zero line clear of the noise inside the band (``checks["probe"]``)."""
    o = truth.optics
    inside = 1.0 / float(length) < 2.0 * o.na / o.wavelength * o.pixel_size
    return inside and bool((m.checks.get("probe") or {}).get("testable"))


#: ``--setting field``: the issue's scenes from another simulator, 1024 x 1024, 150
#: beads, moderate field-varying aberrations (a smear's zero reads deeper in one part of
#: the field than in another)
FIELD_SETTING = {"shape": (1024, 1024), "n_beads": 150, "aberrations": "moderate",
                 "pixel_size": 0.1, "spread": 0.25, "peak_photons": (300.0, 3e4)}
SCENE = {"setting": {}, "optics_type": None}


def scene(seed, length=0.0):
    rng = np.random.default_rng(10_000 + seed)
    angle = float(rng.uniform(0, 180))
    drift = None
    if length:
        a = np.deg2rad(angle)
        drift = (length * np.sin(a), length * np.cos(a))
    extra = dict(SCENE["setting"])
    if SCENE["optics_type"] is not None:
        extra["optics_type"] = SCENE["optics_type"]
    image, truth, params = random_scene(seed, effects={"drift": drift} if drift else None,
                                        **extra)
    return image, truth, angle


def removal_rows(seeds, lengths):
    """The ``--removal`` table (see the module's docstring)."""
    from napari_psfspace.core.model.estimate import estimate_operator
    from napari_psfspace.core.simulation.metrics import grid_errors

    def error(image, truth, remove):
        op = estimate_operator(image, psf_radius=truth.psf_radius, remove_motion=remove)
        return float(np.mean(grid_errors(op, truth, n=6))), op.metadata.get("motion") or {}

    rows = []
    for length in lengths:
        kept, removed, still, found = [], [], [], 0
        for seed in seeds:
            try:
                image, truth, _ = scene(seed, length)
                e_rm, rec = error(image, truth, True)
                if not rec.get("detected"):
                    continue
                clean, ctruth, _ = scene(seed, 0.0)
                e_still = error(clean, ctruth, False)[0]
            except ValueError:  # too few usable beads, in the smeared scene or the still
                continue
            found += 1
            removed.append(e_rm)
            kept.append(error(image, truth, False)[0])
            still.append(e_still)
        def med(v):
            return float(np.median(v)) if v else None
        rows.append({"length_px": length, "found": found, "kept": med(kept),
                     "removed": med(removed), "still": med(still),
                     "share_of_excess_left": (med([(r - c) / max(k - c, 1e-12) for k, r, c
                                                   in zip(kept, removed, still, strict=True)])
                                              if kept else None)})
        print(f"  length {length:g} done", flush=True)
    print("\nField error (6 x 6 grid, against the still optics), median over the scenes "
          "where the smear was found")
    print(table(rows, [("length_px", "g"), ("found", "d"), ("kept", ".4f"),
                       ("removed", ".4f"), ("still", ".4f"),
                       ("share_of_excess_left", ".2f")]))


def astigmatism_rows():
    """Still beads near an astigmatic line focus: how often the motion test reads a line."""
    rows, i = [], 0
    for a in (0.05, 0.1, 0.15, 0.2, 0.3):
        row = {"astig_waves": a}
        for ratio in (0.5, 0.7, 1.0, 1.5):
            hit = tested = 0
            lengths = []
            for px in (0.065, 0.1, 0.13):
                th = np.deg2rad(2 * ((i * 37) % 180))  # the astigmatism's axis turns
                i += 1
                ab = FieldAberrations({5: (a * np.sin(th), 0, 0, 0, 0, 0),
                                       6: (a * np.cos(th), 0, 0, 0, 0, 0),
                                       4: (a * ratio, 0, 0, 0, 0, 0)})
                try:
                    image, truth = simulate_beads((640, 640), 70, aberrations=ab,
                                                  optics=Optics(pixel_size=px), seed=i - 1)
                    est = run_with_progress(iter_estimate(
                        image, psf_radius=truth.psf_radius, holdout=None, n_psf=1))
                except ValueError:  # too few beads placed or kept
                    continue
                m = est.operator.metadata["motion"]
                tested += 1
                hit += bool(m["detected"])
                if m["detected"]:
                    lengths.append(m["length_px"])
            row[f"defocus x{ratio:g}"] = f"{hit}/{tested}"
            row[f"len x{ratio:g}"] = (f"{min(lengths):.1f}-{max(lengths):.1f}" if lengths
                                      else "-")
        rows.append(row)
    cols = [("astig_waves", "g")] + [(f"{k} x{r:g}", "s") for r in (0.5, 0.7, 1.0, 1.5)
                                     for k in ("defocus", "len")]
    print("\nStill beads near an astigmatic line focus: scenes read as a line (of those "
          "tested), and the lengths read (px)")
    print(table(rows, cols))


SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: measured stacks: path, PSF radius (px, or um with the file's pixel size), slices
MEASURED = {
    "sp8_confocal_beads": ("sp8_confocal_beads/sp8_series045_beads_zyx_uint8.tif",
                           ("um", 0.5), range(2, 71, 4)),
    "astigmatic_beads": ("astigmatic_beads/psfextractor_astigmatism_zyx_uint8.tif",
                         ("px", 10.0), range(1, 80, 4)),
    "starfield_2d": ("starfield_2d/dash_starfield_uint16.tif", ("px", 6.0), [None]),
}


def measured_rows():
    """The motion test on slices of every measured stack of ../shared/data."""
    from napari_psfspace.io import read_image

    if not SHARED.is_dir():
        print(f"measured data not found at {SHARED}")
        return
    rows = []
    for name, (path, (unit, r), slices) in MEASURED.items():
        for z in slices:
            image, info = read_image(SHARED / path, index=z)
            radius = r / info.pixel_size if unit == "um" else r
            row = {"set": name, "slice": "-" if z is None else str(z)}
            try:
                est = run_with_progress(iter_estimate(image, psf_radius=radius,
                                                      holdout=None, n_psf=1))
            except ValueError:
                rows.append({**row, "beads": 0, "result": "refused"})
                continue
            m = est.operator.metadata["motion"]
            rows.append({**row, "beads": len(est.patches.psf), "dip_ratio": m["dip_ratio"],
                         "result": ("line read" if m["detected"] else
                                    "not tested" if m["reason"].startswith("not tested")
                                    else "none")})
    print("\nThe motion test on the measured stacks (every 4th slice)")
    print(table(rows, [("set", "s"), ("slice", "s"), ("beads", "d"), ("dip_ratio", ".3f"),
                       ("result", "s")]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--quick", action="store_true", help="20 scenes, lengths 3 and 5")
    ap.add_argument("--astigmatism", action="store_true",
                    help="only the table of still beads near an astigmatic line focus")
    ap.add_argument("--measured", action="store_true",
                    help="only the test on the measured stacks of ../shared/data")
    ap.add_argument("--setting", choices=("family", "field"), default="family",
                    help="'field': the issue's 1024 x 1024 scenes of 150 beads with "
                         "moderate field-varying aberrations")
    ap.add_argument("--generator", choices=("ours", "pyotf"), default="ours",
                    help="the optics code of the PSFs (pyotf: bench/independent.py)")
    ap.add_argument("--removal", action="store_true",
                    help="only the field error with the smear removed, kept, and absent")
    ap.add_argument("--first", type=int, default=0, help="first seed")
    ap.add_argument("--lengths", default=None, help="comma-separated smear lengths (px)")
    args = ap.parse_args()
    if args.setting == "field":
        SCENE["setting"] = FIELD_SETTING
    if args.generator == "pyotf":
        from independent import PyotfOptics

        SCENE["optics_type"] = PyotfOptics
    if args.removal:
        removal_rows(range(args.first, args.first + args.scenes),
                     [float(v) for v in (args.lengths or "3,5").split(",")])
        return
    if args.astigmatism:
        astigmatism_rows()
        return
    if args.measured:
        measured_rows()
        return
    n = 20 if args.quick else args.scenes
    lengths = [3.0, 5.0] if args.quick else [1.5, 2.0, 3.0, 5.0, 8.0]
    if args.lengths:
        lengths = [float(v) for v in args.lengths.split(",")]
    rows = []
    t0 = time.perf_counter()
    for length in [0.0, *lengths]:
        hit = vis = hit_vis = tested = in_band = 0
        len_err, grid_err, ang_err, ratios = [], [], [], []
        for seed in range(args.first, args.first + n):
            try:
                image, truth, angle = scene(seed, length)
                m = motion_of(image, truth, (length, angle) if length else None)
            except ValueError:  # too few beads in this scene
                continue
            tested += 1
            ratios.append(m.dip_ratio)
            in_band += bool(length) and length >= m.min_visible_px
            seen = visible(m, truth, length) if length else False
            vis += seen
            if m.detected:
                hit += 1
                hit_vis += seen
                if length:
                    len_err.append(m.length_px / length - 1)
                    grid = m.checks.get("length_grid_px")
                    if grid is not None:  # the dip route: the zero line's bin
                        grid_err.append(grid / length - 1)
                    d = abs(m.angle_deg - angle) % 180
                    ang_err.append(min(d, 180 - d))
        rows.append({
            "length_px": length, "scenes": tested, "detected": hit / max(tested, 1),
            "in_band": in_band, "visible": vis,
            "found_of_visible": (hit_vis / vis) if vis else None,
            "median_len_err_%": 100 * float(np.median(np.abs(len_err))) if len_err else None,
            "median_len_err_zero_bin_%": (100 * float(np.median(np.abs(grid_err)))
                                          if grid_err else None),
            "median_angle_err": float(np.median(ang_err)) if ang_err else None,
            "min_ratio": float(np.min(ratios)) if ratios else None,
        })
        print(f"  length {length:g}: {time.perf_counter() - t0:.0f} s", flush=True)
    cols = [("length_px", "g"), ("scenes", "d"), ("detected", ".2f"), ("in_band", "d"),
            ("visible", "d"),
            ("found_of_visible", ".2f"), ("median_len_err_%", ".1f"),
            ("median_len_err_zero_bin_%", ".1f"),
            ("median_angle_err", ".1f"), ("min_ratio", ".3f")]
    print("\nMotion blur over the scene set (length 0: effect-free, 'detected' is the "
          "false-alarm rate)")
    print(table(rows, cols))


if __name__ == "__main__":
    main()
