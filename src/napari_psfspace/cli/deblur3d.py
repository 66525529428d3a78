"""``psfspace deblur3d``."""

from __future__ import annotations

import time

from . import common
from .common import COUNT, FINITE, NON_NEGATIVE, existing, progress_printer


def run(args) -> int:
    from ..core.common.progress import run_with_progress
    from ..core.volume import load_operator_3d
    from ..core.volume.deconvolve3d import iter_richardson_lucy_3d
    from ..core.volume.fista3d import iter_deblur_3d
    from ..core.volume.tiles3d import richardson_lucy_3d_tiled
    from ..io import check_output_file, read_stack, write_tiff

    existing(args.model, "--model")
    check_output_file(args.output, "-o")
    if args.scheduler and not args.tile:
        raise ValueError("--scheduler runs tiles: give --tile too")
    if args.method == "sparse" and args.tile:
        raise ValueError("--tile runs Richardson-Lucy only: drop --tile, or use --method rl")
    from ..core.common.device import array_module

    if args.device == "gpu" and args.tile:
        raise ValueError("--device gpu runs on the whole stack (its blocks sized from the "
                         "GPU's memory): drop --tile, or use --device cpu")
    device = array_module("cpu" if args.tile else args.device)
    op = load_operator_3d(args.model)
    stack, info = read_stack(args.stack)
    if stack.shape[1:] != op.shape[1:]:
        raise ValueError(f"STACK {args.stack} has slices of {stack.shape[1:]}, the model "
                         f"{args.model} acts on {op.shape[1:]}")
    t0 = time.perf_counter()
    printer = None if args.quiet else progress_printer()
    from ..core.volume.blocks3d import RTOL

    rtol = RTOL if args.rtol is None else args.rtol
    meta: dict = {"method": args.method, "rtol": rtol}
    if args.method == "sparse":
        res = run_with_progress(iter_deblur_3d(stack, op, max_iter=args.iterations,
                                               rtol=rtol, device=device), printer)
        volume = res.volume
        meta.update(iterations=res.iterations, converged=res.converged,
                    sparse_weight=res.parameters["sparse_weight"],
                    smooth_weight=res.parameters["smooth_weight"],
                    device=res.parameters["device"])
        what = (f"{res.iterations} sparse + smooth iterations on the "
                f"{res.parameters['device'].upper()} "
                f"({'converged' if res.converged else 'stopped at the limit'})")
    elif args.tile:
        client = None
        if args.scheduler:
            from distributed import Client

            client = Client(args.scheduler, timeout=common.SCHEDULER_TIMEOUT)
        try:
            volume = richardson_lucy_3d_tiled(stack, op, n_iter=args.iterations,
                                              background=args.background, tile=args.tile,
                                              rtol=rtol, client=client)
        finally:
            if client is not None:
                client.close()
        meta.update(iterations=args.iterations, tile=args.tile)
        what = f"{args.iterations} Richardson-Lucy iterations on {args.tile} px tiles"
    else:
        res = run_with_progress(iter_richardson_lucy_3d(stack, op, n_iter=args.iterations,
                                                        background=args.background,
                                                        rtol=rtol, device=device), printer)
        volume = res.volume
        meta.update(iterations=res.iterations, background=res.background, device=res.device)
        what = f"{res.iterations} Richardson-Lucy iterations on the {res.device.upper()}"
    write_tiff(args.output, volume, pixel_size=info.pixel_size, metadata={"deblur3d": meta})
    print(f"wrote {args.output}: {what} with the space-varying 3D PSF, "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


def add_parser(sub) -> None:
    d3 = sub.add_parser("deblur3d", help="deblur a z-stack with a space-varying 3D PSF "
                        "(Richardson-Lucy with H and H^T)")
    d3.add_argument("stack", help="TIFF z-stack of the model's lateral size")
    d3.add_argument("--model", required=True, metavar="FILE",
                    help="3D model (psfspace estimate3d)")
    d3.add_argument("-o", "--output", required=True, help="deblurred stack (TIFF, float32)")
    d3.add_argument("--method", choices=("rl", "sparse"), default="rl",
                    help="rl: Richardson-Lucy with H and H^T (default); sparse: sparse + "
                         "smooth (points and a smooth background)")
    d3.add_argument("--iterations", type=COUNT, default=50,
                    help="iterations (sparse: at most)")
    d3.add_argument("--background", type=FINITE,
                    help="rl: constant background (default: the stack's 1st percentile)")
    d3.add_argument("--rtol", type=NON_NEGATIVE,
                    help="largest relative error of a block's PSF against the model's "
                         "(fewer kernels a block; 0: exact; default: the library's, "
                         "napari_psfspace.core.volume.blocks3d.RTOL)")
    d3.add_argument("--tile", type=COUNT,
                    help="rl on lateral tiles of this size through dask (a stack larger "
                         "than memory; 0: the whole stack at once)")
    d3.add_argument("--scheduler", metavar="ADDRESS",
                    help="with --tile: a dask.distributed scheduler to run the tiles on")
    d3.add_argument("--device", choices=("auto", "cpu", "gpu"), default="auto",
                    help="where it runs; auto (default): the GPU when CuPy sees one "
                         "(pip install 'napari-psfspace[gpu]'), else the CPU")
    d3.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    d3.set_defaults(func=run)
