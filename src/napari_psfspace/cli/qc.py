"""``psfspace qc``: a microscope's QC report from one bead z-stack."""

from __future__ import annotations

from .common import COUNT, POSITIVE, add_stack_sampling, progress_printer, stack_sampling


def run(args) -> int:
    import time

    import numpy as np

    from ..core.beads.radius import suggest_psf_radius
    from ..core.common.progress import run_with_progress
    from ..core.volume import iter_estimate_operator_3d
    from ..io import check_output_folder, read_stack
    from ..report.qc import qc_record
    from ..report.qc_page import write_qc_report

    out = check_output_folder(args.output, "-o")
    stack, info = read_stack(args.stack)
    voxel, source, r = stack_sampling(args, info)
    if r is None:  # the widest plane's: from the maximum projection, where every plane shows
        r = suggest_psf_radius(np.asarray(stack).max(axis=0))
    t0 = time.perf_counter()
    est = run_with_progress(iter_estimate_operator_3d(
        stack, psf_radius=r, n_psf=args.n_psf, threshold=args.threshold, voxel_size=voxel),
        None if args.quiet else progress_printer())
    diagnosis = None
    if args.diagnose:  # the 2-D diagnosis of the slice the beads were detected on
        from ..core.diagnosis.loop import iter_diagnose

        focus = int(est.operator.metadata.get("focus_slice", est.operator.plane))
        diagnosis = run_with_progress(
            iter_diagnose(np.asarray(stack)[focus], psf_radius=r, threshold=args.threshold),
            None if args.quiet else progress_printer())
    tol = {k: v for k, v in (("lateral_ratio", args.max_lateral_ratio),
                             ("axial_ratio", args.max_axial_ratio),
                             ("ellipticity", args.max_ellipticity),
                             ("field_flatness", args.max_field_rise)) if v is not None}
    record = qc_record(est, stack, voxel_size=voxel, sampling_from=source, na=args.na,
                       wavelength_nm=args.wavelength_nm, immersion_index=args.immersion_index,
                       tolerances=tol, source=str(args.stack).rsplit("/", 1)[-1],
                       diagnosis=diagnosis)
    paths = write_qc_report(record, est, out, voxel)
    verdict = {True: "PASS", False: "FAIL", None: "not judged (no NA and wavelength)"}
    lat, ax = record["centre_fwhm_lateral_nm"], record["centre_fwhm_axial_nm"]
    print(f"wrote {paths['html']}, {paths['csv'].name}, {paths['json'].name} "
          f"({time.perf_counter() - t0:.0f} s): {verdict[record['passed']]}")
    if lat is not None or ax is not None:
        def nm(v):
            return "not measured" if v is None else f"{v:.0f} nm"

        print(f"  centre: lateral FWHM {nm(lat)}, axial {nm(ax)}")
    for w in record["warnings"]:
        print(f"  warning: {w}")
    return 0


def add_parser(sub) -> None:
    q = sub.add_parser("qc", help="a QC report from a bead z-stack: HTML page, per-bead CSV, "
                       "JSON (FWHM maps, focal surface, theory, pass/fail)")
    q.add_argument("-o", "--output", required=True, help="folder for qc.html, "
                   "qc_beads.csv and qc.json (made if missing)")
    add_stack_sampling(q, radius_required=False,
                       radius_default=" (default: suggested from the maximum projection)")
    q.add_argument("--na", type=POSITIVE, help="numerical aperture (for theory, Nyquist)")
    q.add_argument("--wavelength-nm", type=POSITIVE, help="emission wavelength")
    q.add_argument("--immersion-index", type=POSITIVE,
                   help="immersion refractive index (default from the NA)")
    q.add_argument("--max-lateral-ratio", type=POSITIVE,
                   help="tolerance: lateral FWHM over theory (default 1.5)")
    q.add_argument("--max-axial-ratio", type=POSITIVE,
                   help="tolerance: axial FWHM over theory (default 1.5)")
    q.add_argument("--max-ellipticity", type=POSITIVE, help="tolerance (default 0.2)")
    q.add_argument("--max-field-rise", type=POSITIVE, help="tolerance: the focal "
                   "surface's rise over the field over the axial FWHM (default 1)")
    q.add_argument("--n-psf", type=COUNT, help="basis size I (default: held-out beads)")
    q.add_argument("--threshold", type=POSITIVE, default=8.0,
                   help="detection threshold in noise standard deviations (default 8)")
    q.add_argument("--diagnose", action="store_true", help="also diagnose the best-focus "
                   "slice's 2-D model (its verdict and the effects it adds; slower)")
    q.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    q.set_defaults(func=run, path_inputs={"stack": "STACK"},
                   path_outputs={"output": "-o"})
