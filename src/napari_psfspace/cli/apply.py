"""``psfspace apply``."""

from __future__ import annotations

import time

import numpy as np

from .common import INDEX, existing


def run(args) -> int:
    from ..core.model.operator import load_operator
    from ..io import check_output_file, read_image, write_tiff

    existing(args.model, "MODEL")
    check_output_file(args.output, "-o")
    op = load_operator(args.model)
    image, info = read_image(args.image, index=args.slice)
    if tuple(image.shape) != tuple(op.image_shape):
        raise ValueError(f"IMAGE {args.image} has shape {tuple(image.shape)}, the model "
                         f"{args.model} acts on images of shape {tuple(op.image_shape)}")
    t0 = time.perf_counter()
    out = op.adjoint(image.astype(np.float32)) if args.adjoint else op.apply(
        image.astype(np.float32))
    write_tiff(args.output, out, pixel_size=info.pixel_size)
    print(f"wrote {args.output}: {'adjoint' if args.adjoint else 'blurred'} image "
          f"({time.perf_counter() - t0:.2f} s)")
    return 0


def add_parser(sub) -> None:
    a = sub.add_parser("apply", help="blur an image with a model (H u), or --adjoint")
    a.add_argument("model", help="model file (.npz)")
    a.add_argument("image", help="TIFF image of the model's shape")
    a.add_argument("-o", "--output", required=True, help="output TIFF (float32)")
    a.add_argument("--slice", type=INDEX, help="slice of a stack to use")
    a.add_argument("--adjoint", action="store_true", help="apply the adjoint H^T instead")
    a.set_defaults(func=run, path_inputs={"model": "MODEL", "image": "IMAGE"},
                   path_outputs={"output": "-o"})
