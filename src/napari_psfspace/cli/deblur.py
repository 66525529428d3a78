"""``psfspace deblur``."""

from __future__ import annotations

import os
import sys
import time
import warnings

from .common import COUNT, INDEX, NON_NEGATIVE, existing, progress_printer


def run(args) -> int:
    from ..core.common.device import array_module
    from ..core.common.progress import run_with_progress
    from ..core.model.operator import load_operator
    from ..core.restore import iter_deblur
    from ..io import read_image

    out, option = _checked(args)
    device = array_module(args.device)  # gpu without CuPy or a device: one line, no work
    image, info = read_image(args.image, index=args.slice)
    t0 = time.perf_counter()
    op = (_identified(args, option, image, t0) if args.family is not None
          else load_operator(args.model))
    gen = iter_deblur(image, op, sparse_weight=args.sparse_weight,
                      smooth_weight=args.smooth_weight, max_iter=args.max_iter,
                      debias=args.refit_amplitudes, device=device)
    res = run_with_progress(gen, None if args.quiet else progress_printer())
    written = _written(args, out, res, info)
    p = res.parameters
    print(f"wrote {', '.join(written)}: {res.iterations} iterations on the "
          f"{p['device'].upper()} "
          f"({'converged' if res.converged else 'max_iter reached'}), sparse weight "
          f"{p['sparse_weight']:.3g}, smooth weight {p['smooth_weight']:.3g}, noise sd "
          f"{p['noise_sd']:.3g}, {time.perf_counter() - t0:.1f} s"
          + (f"; {p['saturated_pixels']} saturated pixels (>= {p['saturation']:g}) fitted "
             "as lower bounds" if p["saturated_pixels"] else ""))
    return 0


def _checked(args):
    """The output path and the option that named the family, every path checked before
    any work (the old ``--subspace`` said once, then taken as ``--family``)."""
    from ..io import check_distinct, check_output_file

    out = check_output_file(args.output, "-o")
    option = "--family"
    if args.subspace is not None:  # its old name: said once, then the same run
        from ..core.common.deprecate import message

        print(f"psfspace deblur: FutureWarning: {message('--subspace', '--family')}",
              file=sys.stderr)
        args.family, option = args.subspace, "--subspace"
    if args.parts:
        parts = {f"--parts ({name})": out.with_name(f"{out.stem}.{name}{out.suffix or '.tif'}")
                 for name in ("sparse", "smooth")}
        for path in parts.values():
            check_output_file(path, "--parts")
        check_distinct(parts, {"IMAGE": args.image, "--family": args.family,
                               "--model": args.model, "--beads": args.beads})
    if args.family is not None:
        existing(args.family, option)
    else:
        existing(args.model, "--model")
        if args.beads:
            raise ValueError("--beads identifies an operator of a --family; with --model "
                             "the model is used as it is")
    if args.beads:
        existing(args.beads, "--beads")
    return out, option


def _identified(args, option, image, t0):
    """The image's operator identified from its beads (given or detected) in the family,
    and what the identification says of itself on stderr."""
    from ..core.family.family_file import FORMAT_NAME as FAMILY
    from ..core.family.result import load_family
    from ..core.model.operator_file import archive_format
    from ..core.restore import identify_operator
    from ..core.restore.identify import IdentificationWarning
    from ..io import read_points_csv

    if archive_format(args.family) not in (FAMILY, None):  # None: for the reader
        raise ValueError(f"{option} {args.family} is not a family file (learn one "
                         "with psfspace learn); a single model goes with --model")
    sub = load_family(args.family)
    beads = read_points_csv(args.beads) if args.beads else None
    with warnings.catch_warnings():  # said below, once
        warnings.simplefilter("ignore", IdentificationWarning)
        op = identify_operator(image, sub, beads=beads)
    ident = op.metadata["identification"]
    band = ident.get("error_band")
    left = ident.get("left_out") or []
    print(f"operator identified from {ident['n_beads']} beads "
          f"({'given' if beads is not None else 'detected'}"
          + (f", {len(left)} left out: they disagree with the others" if left else "")
          + f") in {time.perf_counter() - t0:.1f} s; error on them beyond the noise "
          f"{ident['model_error']:.3f}"
          + ("" if band is None else f"; PSF error over the field {band[0]:.3f} to "
                                     f"{band[1]:.3f} (90 % range)"), file=sys.stderr)
    if ident.get("warning"):
        print(f"WARNING: {ident['warning']}", file=sys.stderr)
    return op


def _written(args, out, res, info) -> list[str]:
    """The deblurred image written (with ``--parts``, it and its two parts as one set:
    never a mix of two runs); the paths written."""
    from ..io import write_tiff, write_tiff_set

    source = os.path.basename(os.fspath(args.image))  # each file says what it came from
    meta = {"source": source, "deblur": res.parameters, "iterations": res.iterations}
    members = [(out, res.image, meta)]
    if args.parts:
        members += [(out.with_name(f"{out.stem}.{name}{out.suffix or '.tif'}"), part,
                     {"source": source, "part": name})
                    for name, part in (("sparse", res.sparse), ("smooth", res.smooth))]
        write_tiff_set(members, pixel_size=info.pixel_size)
    else:
        write_tiff(out, res.image, pixel_size=info.pixel_size, metadata=meta)
    return [str(m[0]) for m in members]


def add_parser(sub) -> None:
    db = sub.add_parser("deblur", help="deblur point sources on a smooth background: with "
                        "an operator identified from a family (blind) or a model")
    db.add_argument("image", help="TIFF image (a slice of a stack with --slice)")
    src = db.add_mutually_exclusive_group(required=True)
    src.add_argument("--family", metavar="FILE", help="family of operators (psfspace "
                     "learn): the image's operator is identified from its beads")
    src.add_argument("--subspace", metavar="FILE", help="deprecated: --family")
    src.add_argument("--model", metavar="FILE", help="one operator (psfspace estimate)")
    db.add_argument("--beads", metavar="CSV", help="bead positions to identify from "
                    "(napari Points CSV or row,column; default: detected)")
    db.add_argument("--slice", type=INDEX, help="slice of a stack to deblur")
    db.add_argument("-o", "--output", required=True, help="deblurred image (TIFF, float32: "
                    "sparse + smooth parts)")
    db.add_argument("--parts", action="store_true", help="also write OUT.sparse.tif and "
                    "OUT.smooth.tif")
    db.add_argument("--sparse-weight", type=NON_NEGATIVE, help="gamma1 (default: from the noise)")
    db.add_argument("--smooth-weight", type=NON_NEGATIVE, help="gamma2 (default: 0.05 step^4)")
    db.add_argument("--max-iter", type=COUNT, default=500)
    db.add_argument("--refit-amplitudes", action="store_true",
                    help="then refit each cluster of points' flux by least squares (the l1 "
                         "term shrinks it; also raises spurious points: see deblur's "
                         "`debias`)")
    db.add_argument("--device", choices=("auto", "cpu", "gpu"), default="auto",
                    help="where the operator's transforms run; auto (default): the GPU "
                         "when CuPy sees one (pip install 'napari-psfspace[gpu]'), else "
                         "the CPU")
    db.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    db.set_defaults(func=run, path_inputs={"image": "IMAGE", "family": "--family",
                                      "subspace": "--subspace", "model": "--model",
                                      "beads": "--beads"},
                    path_outputs={"output": "-o"})
