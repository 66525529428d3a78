"""``psfspace simulate``."""

from __future__ import annotations

import numpy as np

from .common import COUNT, INDEX, number

#: ``simulate --focus-series``: the foci span +-this (micrometres).
SERIES_HALF_RANGE_UM = 0.6


def run(args) -> int:
    from ..core.simulation import simulate_beads
    from ..io import check_output_file, write_tiff, write_tiff_set

    check_output_file(args.output, "-o")
    if args.truth_grid:
        check_output_file(args.truth_grid, "--truth-grid")
    if args.focus_series:
        if args.truth_grid:
            raise ValueError("--truth-grid is for one image; a --focus-series has one "
                             "PSF field per slice")
        return simulate_series(args)
    image, truth = simulate_beads(tuple(args.shape), args.beads, aberrations=args.aberrations,
                                  seed=args.seed)
    meta = {"psf_radius": truth.psf_radius, "n_beads": int(len(truth.positions)),
            "aberrations": args.aberrations, "seed": args.seed}
    if args.truth_grid:  # the image and its true PSFs: one set, never two runs' files
        ys, xs, psfs = truth.psf_grid(8, 8)
        write_tiff_set([(args.output, image, meta),
                        (args.truth_grid, psfs.reshape(-1, *psfs.shape[2:]), None)],
                       pixel_size=truth.optics.pixel_size)
    else:
        write_tiff(args.output, image, pixel_size=truth.optics.pixel_size, metadata=meta)
    print(f"wrote {args.output}: {image.shape[0]}x{image.shape[1]} {image.dtype}, "
          f"{len(truth.positions)} beads, suggested --psf-radius {truth.psf_radius}")
    if args.truth_grid:
        print(f"wrote {args.truth_grid}: true PSFs on an 8x8 grid")
    return 0


def simulate_series(args) -> int:
    """``simulate --focus-series N``: one bead field at N foci from -0.6 to 0.6 µm."""
    from ..core.simulation.focus import simulate_focus_series
    from ..io import write_tiff

    z_um = np.linspace(-SERIES_HALF_RANGE_UM, SERIES_HALF_RANGE_UM, args.focus_series)
    stack, series = simulate_focus_series(tuple(args.shape), args.beads, z_um,
                                          aberrations=args.aberrations, seed=args.seed)
    meta = {"psf_radius": int(series.psf_radius.max()), "z_um": series.z_um.tolist(),
            "n_beads": args.beads, "aberrations": args.aberrations, "seed": args.seed}
    write_tiff(args.output, stack, pixel_size=series.optics.pixel_size, metadata=meta)
    print(f"wrote {args.output}: {stack.shape[0]} slices of {stack.shape[1]}x"
          f"{stack.shape[2]} {stack.dtype} at foci {z_um[0]:+.2f} to {z_um[-1]:+.2f} um, "
          f"{args.beads} beads; widest PSF radius {meta['psf_radius']} px")
    return 0


def add_parser(sub) -> None:
    s = sub.add_parser("simulate", help="simulate a bead image with a known PSF field")
    s.add_argument("-o", "--output", required=True, help="output TIFF")
    s.add_argument("--shape", type=number("int", low=16), nargs=2, default=(1024, 1024),
                   metavar=("ROWS", "COLS"))
    s.add_argument("--beads", type=COUNT, default=150, help="number of beads (default 150)")
    s.add_argument("--aberrations", choices=("none", "moderate", "strong"), default="moderate")
    s.add_argument("--seed", type=INDEX, default=0)
    s.add_argument("--truth-grid", help="also write the true PSFs on an 8x8 grid to this TIFF")
    s.add_argument("--focus-series", type=number("int", low=2), metavar="N",
                   help="write a stack instead: the same beads at N foci from -0.6 to "
                        "0.6 um (a family of conditions for `psfspace learn`)")
    s.set_defaults(func=run, path_inputs={},
                   path_outputs={"output": "-o", "truth_grid": "--truth-grid"})
