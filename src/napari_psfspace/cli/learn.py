"""``psfspace learn``."""

from __future__ import annotations

import sys

from . import common
from .common import COUNT, POSITIVE, progress_printer


def run(args) -> int:
    from ..core.beads.radius import suggest_series_radius
    from ..core.common.errors import NoBeadsError
    from ..core.common.progress import run_with_progress
    from ..core.common.validate import check_psf_radius
    from ..core.family import iter_estimate_family
    from ..core.family.estimate import max_space
    from ..io import check_output_file, read_image, read_slice, stack_loaders

    check_output_file(args.output, "-o")
    loaders, labels = stack_loaders(args.inputs, args.slices)
    if len(loaders) < 2:
        raise ValueError(f"learn needs at least 2 images (conditions), got {len(loaders)}: "
                         "pass several TIFFs, a folder, or a stack (with --slices)")
    r = args.psf_radius
    first, info = read_image(loaders[0].args[0], index=loaders[0].args[1])
    if r is None:
        if args.psf_radius_um is not None:
            if not info.pixel_size:
                raise ValueError("--psf-radius-um needs the pixel size, which the file does "
                                 "not give: pass --psf-radius in pixels instead.")
            r = args.psf_radius_um / info.pixel_size
        else:
            try:  # the middle image first, then outwards
                r, i = suggest_series_radius(lambda k: read_slice(*loaders[k].args),
                                             len(loaders))
            except NoBeadsError:
                raise ValueError("no --psf-radius given and none could be measured on the "
                                 "middle images (no bright spot stands out of the noise): "
                                 "give --psf-radius") from None
            print(f"no --psf-radius given: using {r:g} px, measured from {labels[i]}",
                  file=sys.stderr)
    try:  # before any work (the bound below would allocate a window of that radius)
        check_psf_radius(r, first.shape[-2:])
    except ValueError as exc:
        option = "--psf-radius" if args.psf_radius is not None else "--psf-radius-um"
        raise ValueError(f"{option}: {exc}".replace("`psf_radius`", "the PSF radius")
                         ) from None
    most = max_space(len(loaders), args.n_psf, psf_radius=r)
    if args.n_space is not None and args.n_space > most:
        raise ValueError(f"--n-space {args.n_space} is more spatial maps than {len(loaders)} "
                         f"images give: at most {most}")
    client = None
    if args.scheduler:
        try:
            from distributed import Client
        except ImportError:
            raise ValueError("--scheduler needs dask.distributed: pip install "
                             "'napari-psfspace[cluster]'") from None
        try:
            client = Client(args.scheduler, timeout=common.SCHEDULER_TIMEOUT)
        except (OSError, TimeoutError) as exc:
            raise ValueError(f"--scheduler {args.scheduler}: no dask scheduler answered "
                             f"within {common.SCHEDULER_TIMEOUT} ({type(exc).__name__})") from None
    try:
        gen = iter_estimate_family(loaders, psf_radius=r, n_psf=args.n_psf,
                                     n_space=args.n_space, client=client,
                                     threshold=args.threshold)
        sub = run_with_progress(gen, None if args.quiet else progress_printer())
    finally:
        if client is not None:
            client.close()
    sub.metadata["inputs"] = [labels[k] for k in sub.metadata["images"]]
    sub.save(args.output)
    m = sub.metadata
    print(f"wrote {args.output}: {sub.n_images} images, I = {sub.n_psf} PSFs, J = "
          f"{sub.n_space} spatial maps, {sum(m['beads_per_image'])} beads")
    for k, why in m["skipped"].items():
        print(f"skipped {labels[int(k)]}: {why}")
    return 0


def add_parser(sub) -> None:
    ln = sub.add_parser("learn", help="learn the family of a microscope's operators from "
                        "bead images under many conditions")
    ln.add_argument("inputs", nargs="+", metavar="INPUT",
                    help="TIFF images (one per condition), a folder of them, or a stack "
                         "whose slices are the conditions")
    ln.add_argument("-o", "--output", required=True, help="family file to write (.npz)")
    g = ln.add_mutually_exclusive_group()
    g.add_argument("--psf-radius", type=POSITIVE,
                   help="PSF radius r in pixels (default: suggested from the first image)")
    g.add_argument("--psf-radius-um", type=POSITIVE,
                   help="PSF radius in micrometres (needs the pixel size in the TIFF)")
    ln.add_argument("--slices", metavar="A:B", help="slices A to B-1 of a stack")
    ln.add_argument("--n-psf", type=COUNT, help="PSF basis size I (default: Gavish-Donoho)")
    ln.add_argument("--n-space", type=COUNT, help="spatial basis size J (default: the rule)")
    ln.add_argument("--threshold", type=POSITIVE, default=8.0,
                    help="detection threshold in noise standard deviations (default 8)")
    ln.add_argument("--scheduler", metavar="ADDRESS",
                    help="run on this dask.distributed scheduler (default: this machine)")
    ln.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    ln.set_defaults(func=run, path_inputs={"inputs": "INPUT"},
                    path_outputs={"output": "-o"})
