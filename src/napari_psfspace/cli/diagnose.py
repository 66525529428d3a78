"""``psfspace diagnose``."""

from __future__ import annotations

import sys
from pathlib import Path

from .common import (
    COUNT,
    FINITE,
    NON_NEGATIVE,
    POSITIVE,
    add_radius_and_slice,
    bead_diameter_px,
    image_and_radius,
    progress_printer,
)


def run(args) -> int:
    from ..core.common.measures import field_fwhm, fwhm_line
    from ..core.common.progress import run_with_progress
    from ..core.diagnosis.loop import iter_diagnose
    from ..core.model.fewbeads import one_psf_note
    from ..io import check_output_file, check_output_folder
    from ..report import model_lines, summary_text, write_report

    if args.read_noise is not None and args.gain is None:
        raise ValueError("--read-noise needs --gain and --offset: give the three camera "
                         "values together (or only --offset).")
    check_output_folder(args.report, "--report")
    if args.model:
        check_output_file(args.model, "--model")
    image, info, r = image_and_radius(args)
    gen = iter_diagnose(image, psf_radius=r, threshold=args.threshold, gain=args.gain,
                        offset=args.offset, read_noise=args.read_noise, n_psf=args.n_psf,
                        smoothing=args.smoothing, bead_diameter=bead_diameter_px(args, info),
                        remove_motion=args.remove_motion)
    diag = run_with_progress(gen, None if args.quiet else progress_printer(sys.stderr))
    print(summary_text(diag))
    for line in model_lines(diag.operator.metadata, markdown=False):
        print(line)
    print(fwhm_line(field_fwhm(diag.operator), info.pixel_size,
                    one_psf=one_psf_note(diag.operator.metadata)))
    extra = {"source": str(args.image), "slice": args.slice}
    path = write_report(diag, args.report, image_name=Path(args.image).name,
                        pixel_size=info.pixel_size, extra=extra)
    print(f"wrote {path} with report.json and figures in {path.parent}/")
    if args.model:
        op = diag.operator
        op = type(op)(op.basis, op.coefficients, shape=op.image_shape, grid=op.grid,
                      metadata={**op.metadata, "pixel_size_um": info.pixel_size, **extra})
        op.save(args.model)
        print(f"wrote {args.model}: refined model, basis of {op.n_psf} PSFs of "
              f"{op.psf_size} px")
    return 0


def add_parser(sub) -> None:
    dg = sub.add_parser("diagnose", help="trace the model's held-out residual to what it "
                        "lacks, add it, write a report")
    dg.add_argument("image", help="TIFF bead image in ADU (2-D, or a stack with --slice)")
    dg.add_argument("--report", required=True, metavar="DIR",
                    help="folder for report.md, report.json and the figures")
    add_radius_and_slice(dg)
    dg.add_argument("--gain", type=POSITIVE,
                    help="camera gain in ADU per electron (with --offset and --read-noise; "
                         "default: noise model measured on the image)")
    dg.add_argument("--offset", type=FINITE, help="camera offset in ADU")
    dg.add_argument("--read-noise", type=NON_NEGATIVE, help="camera read noise in electrons rms")
    dg.add_argument("--threshold", type=POSITIVE, default=8.0,
                    help="detection threshold in noise standard deviations (default 8)")
    dg.add_argument("--n-psf", type=COUNT, help="diagnose a model of this basis size "
                    "(default: chosen from the beads)")
    dg.add_argument("--smoothing", type=NON_NEGATIVE, help="diagnose a model of this thin-plate "
                    "smoothing (default: chosen from the beads)")
    dg.add_argument("--model", metavar="OUT.npz", help="also save the refined model")
    dg.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    dg.set_defaults(func=run, path_inputs={"image": "IMAGE"},
                    path_outputs={"report": "--report", "model": "--model"})
