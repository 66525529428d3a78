"""``psfspace psf``."""

from __future__ import annotations

from .common import FINITE, INDEX, existing


def run(args) -> int:
    from ..core.family.family_file import FORMAT_NAME as FAMILY
    from ..core.family.result import load_family
    from ..core.model.operator import load_operator
    from ..core.model.operator_file import archive_format
    from ..io import check_output_file, write_tiff

    existing(args.model, "MODEL")
    check_output_file(args.output, "-o")
    if archive_format(args.model) == FAMILY:
        sub = load_family(args.model)
        if args.image is None:
            raise ValueError(f"{args.model} is a family of {sub.n_images} images: pass "
                             f"--image K (0 to {sub.n_images - 1})")
        if not args.image < sub.n_images:
            raise ValueError(f"--image {args.image} is out of range: {args.model} holds "
                             f"{sub.n_images} images (0 to {sub.n_images - 1})")
        op = sub.operator(args.image)
    elif args.image is not None:
        raise ValueError(f"--image is for a family; {args.model} is a single model")
    else:
        op = load_operator(args.model)
    y, x = args.at
    from ..core.model.psf_field import check_in_field

    try:
        check_in_field(y, x, op.image_shape)
    except ValueError as exc:
        raise ValueError(f"--at {y} {x}: {str(exc).split(' = ', 1)[-1]}") from None
    psf = op.psf_at(y, x)
    write_tiff(args.output, psf, pixel_size=op.metadata.get("pixel_size_um"),
               metadata={"row": y, "column": x})
    print(f"wrote {args.output}: PSF at row {y}, column {x} ({psf.shape[0]}x{psf.shape[1]}, "
          "sum 1)")
    return 0


def add_parser(sub) -> None:
    f = sub.add_parser("psf", help="write the PSF of a model (or of image K of a family) "
                       "at a field position")
    f.add_argument("model", help="model or family file (.npz)")
    f.add_argument("--image", type=INDEX, metavar="K", help="image K of a family")
    f.add_argument("--at", type=FINITE, nargs=2, required=True, metavar=("ROW", "COL"))
    f.add_argument("-o", "--output", required=True, help="output TIFF")
    f.set_defaults(func=run, path_inputs={"model": "MODEL"},
                   path_outputs={"output": "-o"})
