"""``psfspace estimate``."""

from __future__ import annotations

from .common import (
    NON_NEGATIVE,
    POSITIVE,
    add_radius_and_slice,
    bead_diameter_px,
    image_and_radius,
    n_psf_choice,
    number,
    progress_printer,
)


def run(args) -> int:
    from ..core.common.measures import field_fwhm, fwhm_line
    from ..core.common.progress import run_with_progress
    from ..core.diagnosis.loop import iter_heldout_error
    from ..core.model.estimate import iter_estimate
    from ..core.model.fewbeads import one_psf_note
    from ..io import check_output_file
    from ..report import model_lines

    check_output_file(args.output, "-o")
    image, info, r = image_and_radius(args)
    n_psf = args.n_psf
    gen = iter_estimate(image, psf_radius=r, n_psf=n_psf, smoothing=args.smoothing,
                        threshold=args.threshold, holdout=args.holdout or None,
                        bead_diameter=bead_diameter_px(args, info),
                        remove_motion=args.remove_motion)
    est = run_with_progress(gen, None if args.quiet else progress_printer())
    # the one accuracy figure (core/diagnosis/metric.py), by the code Diagnose uses
    try:
        held = run_with_progress(
            iter_heldout_error(image, psf_radius=r, threshold=args.threshold,
                               n_psf=n_psf if isinstance(n_psf, int) else None,
                               smoothing=args.smoothing,
                               bead_diameter=bead_diameter_px(args, info)),
            None if args.quiet else progress_printer())
    except ValueError as exc:  # e.g. too few beads to judge each by the others
        held = str(exc)
    op = est.operator
    op = type(op)(op.basis, op.coefficients, shape=op.image_shape, grid=op.grid,
                  metadata={**op.metadata, "heldout_error": (
                      held if isinstance(held, str) else held.to_dict()),
                            **({"pixel_size_um": info.pixel_size, "source": str(args.image),
                                "slice": args.slice} if info.pixel_size else {})})
    op.save(args.output)
    meta = op.metadata
    print(f"wrote {args.output}: basis of {op.n_psf} PSFs of {op.psf_size} px from "
          f"{meta['n_beads_used']} beads; {est.beads.summary()}")
    print(f"held-out error not measured: {held}" if isinstance(held, str) else held.line())
    for line in model_lines(meta, markdown=False):
        print(line)
    print(fwhm_line(field_fwhm(op), info.pixel_size,
                    one_psf=one_psf_note(op.metadata)))
    return 0


def add_parser(sub) -> None:
    e = sub.add_parser("estimate", help="estimate the operator from a bead image")
    e.add_argument("image", help="TIFF bead image (2-D, or a stack with --slice)")
    e.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    add_radius_and_slice(e)
    e.add_argument("--n-psf", type=n_psf_choice,
                   help="basis size I, or 'heldout' (default) or 'rule'")
    e.add_argument("--smoothing", type=NON_NEGATIVE,
                   help="thin-plate smoothing eta (default: LOO CV)")
    e.add_argument("--threshold", type=POSITIVE, default=8.0,
                   help="detection threshold in noise standard deviations (default 8)")
    e.add_argument("--holdout", type=number("float", low=0, high=0.5), default=0.2,
                   help="fraction of beads held out to measure the error (0 to skip)")
    e.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    e.set_defaults(func=run, path_inputs={"image": "IMAGE"},
                   path_outputs={"output": "-o"})
