"""``psfspace estimate3d``."""

from __future__ import annotations

import numpy as np

from .common import COUNT, POSITIVE, add_stack_sampling, progress_printer, stack_sampling


def run(args) -> int:
    from ..core.common.measures import NAMES, in_units
    from ..core.common.progress import run_with_progress
    from ..core.volume import iter_estimate_operator_3d
    from ..core.volume.measures import (
        bead_measures,
        direct_bead_measures,
        map_uncertainty,
        measure_maps,
        measure_table,
    )
    from ..io import check_output_file, read_stack

    check_output_file(args.output, "-o")
    if args.table:
        check_output_file(args.table, "--table")
    stack, info = read_stack(args.stack)
    voxel, _, r = stack_sampling(args, info)
    est = run_with_progress(iter_estimate_operator_3d(
        stack, psf_radius=r, z_radius=args.z_radius, n_psf=args.n_psf,
        threshold=args.threshold, voxel_size=voxel),
        None if args.quiet else progress_printer())
    op = est.operator
    op.save(args.output)
    inl = est.basis.inliers
    beads = bead_measures(est.patches.subset(inl))
    unc = map_uncertainty(op, beads, est.patches.centers[inl])
    _, _, maps = measure_maps(op, 4, 4)
    print(f"wrote {args.output}: {op.n_psf} 3D PSFs of {'x'.join(map(str, op.kernel_shape))} "
          f"voxels from {op.metadata['n_beads_used']} beads, bead plane {op.plane}")
    print("  measures (Gaussian fits with an offset, as napari-psf-analysis quotes them; "
          + ("nm" if voxel else "px and planes: pass --pixel-size-nm and --z-step-nm for nm")
          + "):")
    for name in NAMES:
        seen = maps[name][np.isfinite(maps[name])]
        lo, lo_u = in_units({name: float(seen.min()) if seen.size else np.nan}, voxel)
        hi, _ = in_units({name: float(seen.max()) if seen.size else np.nan}, voxel)
        sd, _ = in_units({name: unc[name]}, voxel)
        unit = f" {lo_u[name]}" if lo_u[name] else ""
        what = "focal_plane (from the first plane)" if name == "focal_plane" else name
        if not np.isfinite(lo[name]):
            print(f"  {what}: not measurable over the field")
            continue
        spread = (f"+- {sd[name]:.2g} between the beads and the model"
                  if np.isfinite(sd[name]) else "fewer than 3 beads to compare with the model")
        print(f"  {what}: {lo[name]:.3g} to {hi[name]:.3g}{unit} over the field ({spread})")
    held = op.metadata.get("heldout")
    if held and held.get("n_beads"):
        print(f"  held-out beads ({held['n_beads']}): residual {held['residual_median']:.3f}, "
              f"{held['over_floor']:.2f}x their noise floor ({held['noise_kind']}); one 3D "
              f"PSF {held['single_median']:.3f}")
    if op.metadata.get("field_model") == "shift-invariant":
        print(f"  one 3D PSF for the field: {op.metadata['field_model_reason']}")
    if args.table:
        import csv

        from ..core.common.atomic import atomic_write

        # each bead fitted to its own pixels, as the microscopist's own fit reads it
        rows = measure_table(direct_bead_measures(stack, est), est.patches.centers[inl],
                             voxel)

        def write(fh):
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)

        atomic_write(args.table, write, mode="w", encoding="utf-8", newline="")
        print(f"wrote {args.table}: {len(rows)} beads' direct fits")
    return 0


def add_parser(sub) -> None:
    e3 = sub.add_parser("estimate3d", help="learn the space-varying 3D PSF from a bead "
                        "z-stack; print its maps (focal shift, FWHM, astigmatism)")
    e3.add_argument("-o", "--output", required=True, help="3D model file to write (.npz)")
    add_stack_sampling(e3, radius_required=True, radius_default="")
    e3.add_argument("--z-radius", type=COUNT, help="planes kept on each side of the bead "
                    "plane (default: the whole stack)")
    e3.add_argument("--n-psf", type=COUNT, help="basis size I (default: held-out beads)")
    e3.add_argument("--threshold", type=POSITIVE, default=8.0,
                    help="detection threshold in noise standard deviations (default 8)")
    e3.add_argument("--table", metavar="CSV", help="also write each bead's direct fits")
    e3.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    e3.set_defaults(func=run, path_inputs={"stack": "STACK"},
                    path_outputs={"output": "-o", "table": "--table"})
