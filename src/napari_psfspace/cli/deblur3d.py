"""``psfspace deblur3d``."""

from __future__ import annotations

import time

from . import common
from .common import COUNT, FINITE, NON_NEGATIVE, POSITIVE, existing, progress_printer


def run(args) -> int:
    from ..core.common.progress import run_with_progress
    from ..core.volume import load_operator_3d
    from ..core.volume.deconvolve3d import iter_richardson_lucy_3d
    from ..core.volume.fista3d import iter_deblur_3d
    from ..deblur_store import is_zarr_path, stack_voxel_size
    from ..io import check_output_file, read_stack, write_tiff

    existing(args.model, "--model")
    tiled = bool(args.tile or args.memory or args.resume)
    if not args.resume and not is_zarr_path(args.output):
        check_output_file(args.output, "-o")
    if args.scheduler and not tiled:
        raise ValueError("--scheduler runs tiles: give --memory or --tile too")
    if args.method == "sparse" and tiled:
        raise ValueError("--memory, --tile and --resume run Richardson-Lucy only: use "
                         "--method rl")
    if is_zarr_path(args.output) and not tiled:
        raise ValueError("an OME-Zarr output (-o *.zarr) is written tile by tile: give "
                         "--memory (e.g. --memory 4GB) or --tile")
    from ..core.common.device import array_module

    device = array_module(args.device)  # "gpu" without one: one line, before any work
    op = load_operator_3d(args.model)
    if tiled:
        return _run_tiled(args, op)
    stack, info = read_stack(args.stack)
    if stack.shape[1:] != op.image_shape[1:]:
        raise ValueError(f"STACK {args.stack} has slices of {stack.shape[1:]}, the model "
                         f"{args.model} acts on {op.image_shape[1:]}")
    voxel = stack_voxel_size(op, info, voxel_size=_given_voxel(args),
                             name=f"STACK {args.stack}")
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
    else:
        res = run_with_progress(iter_richardson_lucy_3d(stack, op, n_iter=args.iterations,
                                                        background=args.background,
                                                        rtol=rtol, device=device), printer)
        volume = res.volume
        meta.update(iterations=res.iterations, background=res.background, device=res.device)
        what = f"{res.iterations} Richardson-Lucy iterations on the {res.device.upper()}"
    write_tiff(args.output, volume, pixel_size=info.pixel_size if voxel is None else voxel[2],
               z_spacing=None if voxel is None else voxel[0], metadata={"deblur3d": meta})
    print(f"wrote {args.output}: {what} with the space-varying 3D PSF, "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


def _run_tiled(args, op) -> int:
    """Richardson-Lucy on tiles that exchange their margins, from the file, the
    iterates beside the output, resumable (:mod:`napari_psfspace.deblur_store`)."""
    from ..core.volume.blocks3d import RTOL
    from ..deblur_store import deblur_to_store

    client = None
    if args.scheduler:
        from distributed import Client

        client = Client(args.scheduler, timeout=common.SCHEDULER_TIMEOUT)
    t0 = time.perf_counter()
    try:
        run = deblur_to_store(args.stack, op, args.output, n_iter=args.iterations,
                              memory=args.memory, tile=args.tile or None,
                              background=args.background,
                              rtol=RTOL if args.rtol is None else args.rtol,
                              resume=args.resume, client=client,
                              voxel_size=_given_voxel(args), device=args.device,
                              progress=None if args.quiet else progress_printer())
    finally:
        if client is not None:
            client.close()
    print(f"wrote {args.output}: {run.iterations} Richardson-Lucy iterations on {run.tile} "
          f"px tiles on the {run.device.upper()} exchanging their margins "
          f"({run.chunks_written} of {run.chunks_total} chunks written by this run), "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


def _given_voxel(args) -> tuple | None:
    """--z-step-nm and --pixel-size-nm as a voxel size (dz, dy, dx) in µm, None where
    neither is given (each missing one is the file's)."""
    if not (args.pixel_size_nm or args.z_step_nm):
        return None
    px = args.pixel_size_nm / 1000.0 if args.pixel_size_nm else None
    return (args.z_step_nm / 1000.0 if args.z_step_nm else None, px, px)


def _bytes(text: str) -> float:
    """A memory size such as ``4GB``, ``512MiB`` or ``2e9`` (bytes), for argparse."""
    import argparse

    from dask.utils import parse_bytes

    try:
        value = float(parse_bytes(text))
    except (ValueError, TypeError):
        raise argparse.ArgumentTypeError(f"expected a memory size such as 4GB or 512MiB, "
                                         f"got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive memory size, got {text!r}")
    return value


def add_parser(sub) -> None:
    d3 = sub.add_parser("deblur3d", help="deblur a z-stack with a space-varying 3D PSF "
                        "(Richardson-Lucy with H and H^T)")
    d3.add_argument("stack", help="z-stack of the model's lateral size: TIFF or OME-Zarr")
    d3.add_argument("--model", required=True, metavar="FILE",
                    help="3D model (psfspace estimate3d)")
    d3.add_argument("-o", "--output", required=True,
                    help="deblurred stack, float32: TIFF, or OME-Zarr (*.zarr, with "
                         "--memory or --tile)")
    d3.add_argument("--pixel-size-nm", type=POSITIVE,
                    help="the stack's pixel size (overrides the file's); checked against "
                         "the model's")
    d3.add_argument("--z-step-nm", type=POSITIVE,
                    help="the stack's plane spacing (overrides the file's)")
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
    d3.add_argument("--memory", type=_bytes, metavar="SIZE",
                    help="rl on lateral tiles that exchange their margins every iteration "
                         "(the whole stack's result), sized to hold at most SIZE (e.g. "
                         "4GB); the stack is read a piece at a time and the iterates kept "
                         "beside the output (OUTPUT.iterates)")
    d3.add_argument("--tile", type=COUNT,
                    help="as --memory, with tiles of this size (pixels) instead")
    d3.add_argument("--resume", action="store_true",
                    help="finish an interrupted --memory/--tile run of the same output "
                         "from its last iteration and the chunks it wrote")
    d3.add_argument("--scheduler", metavar="ADDRESS",
                    help="with --memory or --tile: a dask.distributed scheduler to run "
                         "the tiles on")
    d3.add_argument("--device", choices=("auto", "cpu", "gpu"), default="auto",
                    help="where it runs; auto (default): the GPU when CuPy sees one "
                         "(pip install 'napari-psfspace[gpu]'), else the CPU; with "
                         "--memory or --tile, each tile's blocks on it (with "
                         "--scheduler, each worker's own device)")
    d3.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    d3.set_defaults(func=run, path_inputs={"stack": "STACK", "model": "--model"},
                    path_outputs={"output": "-o"})
