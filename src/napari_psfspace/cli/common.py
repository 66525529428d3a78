"""What every command of the command line shares: the argparse types that name a bad
value before any work, the checks of input files, the PSF radius (given, in micrometres or
measured), the progress lines, and the parser whose errors are one line."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

#: How long ``--scheduler`` (learn, deblur3d) waits for the scheduler to answer.
SCHEDULER_TIMEOUT = "10s"


def progress_printer(stream=None):
    start = time.perf_counter()
    last: list = []

    def show(p):
        if last == [p]:  # a long step's repeated record (it is still running)
            return
        last[:] = [p]
        print(f"[{100 * p.fraction:5.1f}% {time.perf_counter() - start:6.1f}s] {p.stage}: "
              f"{p.message}", file=stream or sys.stderr, flush=True)

    return show


def number(kind: str, *, low: float | None = None, high: float | None = None,
            low_open: bool = False, high_open: bool = False):
    """An argparse ``type`` for a finite number in a range: a bad value makes argparse
    name the option and exit 2 before any work."""
    def parse(text: str):
        try:
            v = int(text) if kind == "int" else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'a whole number' if kind == 'int' else 'a number'}, got "
                f"{text!r}") from None
        bad = not np.isfinite(v)
        if low is not None:
            bad |= v <= low if low_open else v < low
        if high is not None:
            bad |= v >= high if high_open else v > high
        if bad:
            lo = "" if low is None else f"{'>' if low_open else '>='} {low:g}"
            hi = "" if high is None else f"{'<' if high_open else '<='} {high:g}"
            raise argparse.ArgumentTypeError(
                f"expected a finite number {' and '.join(x for x in (lo, hi) if x)}, got "
                f"{text!r}")
        return v
    parse.__name__ = kind  # argparse's "invalid <name> value" when it is not ours
    return parse


POSITIVE = number("float", low=0, low_open=True)
NON_NEGATIVE = number("float", low=0)
FINITE = number("float")
COUNT = number("int", low=1)
INDEX = number("int", low=0)


def n_psf_choice(text: str):
    """--n-psf: a whole number >= 1, or 'heldout' / 'rule'."""
    if text in ("heldout", "rule"):
        return text
    try:
        return COUNT(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected a whole number >= 1, 'heldout' or 'rule', got {text!r}") from None


def existing(path: str, option: str) -> str:
    """An input file that must exist (checked before any work)."""
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{option} {path}: is a folder, expected a file")
    if not p.exists():
        raise ValueError(f"{option} {path}: no such file")
    return path


def psf_radius_px(args, info) -> float | None:
    if args.psf_radius is not None:
        return args.psf_radius
    if args.psf_radius_um is not None:
        if not info.pixel_size:
            raise ValueError(
                "--psf-radius-um needs the pixel size, which the file does not give: "
                "pass --psf-radius in pixels instead."
            )
        return args.psf_radius_um / info.pixel_size
    return None


def image_and_radius(args):
    """The image (a slice of a stack), what the file says of it, and the PSF radius in
    pixels: given in pixels or micrometres, else measured from the image."""
    from ..io import read_image

    image, info = read_image(args.image, index=args.slice)
    if getattr(args, "pixel_size_nm", None) is not None:
        if not args.pixel_size_nm > 0:
            raise ValueError(f"--pixel-size-nm must be > 0, got {args.pixel_size_nm}.")
        info = dataclasses.replace(info, pixel_size=args.pixel_size_nm / 1000.0)
    r = psf_radius_px(args, info)
    if r is None and args.slice is None:
        from ..core.beads.radius import suggest_psf_radius

        r = suggest_psf_radius(image)
        print(f"no --psf-radius given: using {r:g} px, measured from the image "
              "(see suggest_psf_radius)", file=sys.stderr)
    elif r is None:  # a slice of a stack: from it and its neighbours, against focus
        from ..core.beads.focus import radius_against_focus
        from ..core.beads.slice_radius import suggest_slice_radius
        from ..io import read_stack

        stack = read_stack(args.image)[0]
        found = suggest_slice_radius(stack, args.slice)
        r = found.radius
        print(f"no --psf-radius given: using {r:g} px, measured from slice {args.slice} "
              "and its neighbours (see suggest_slice_radius)", file=sys.stderr)
        for why in (found.reason, radius_against_focus(stack, args.slice, r)):
            if why:
                print(why, file=sys.stderr)
    return image, info, r


def stack_sampling(args, info):
    """A z-stack's voxel size ``(dz, dy, dx)`` in µm (None unless both are known) from
    ``--pixel-size-nm``/``--z-step-nm`` or the file, where it came from ("given",
    "file", "unknown"), and the PSF radius in pixels from ``--psf-radius`` or
    ``--psf-radius-um`` (None where neither is given)."""
    pixel = args.pixel_size_nm / 1000.0 if args.pixel_size_nm else info.pixel_size
    dz = args.z_step_nm / 1000.0 if args.z_step_nm else info.z_spacing
    voxel = (dz, pixel, pixel) if pixel and dz else None
    source = ("given" if args.pixel_size_nm or args.z_step_nm
              else "file" if voxel else "unknown")
    r = args.psf_radius
    if r is None and args.psf_radius_um is not None:
        if not pixel:
            raise ValueError("--psf-radius-um needs the pixel size, which the file does not "
                             "give: pass --pixel-size-nm or --psf-radius in pixels")
        r = args.psf_radius_um / pixel
    return voxel, source, r


def add_stack_sampling(parser: argparse.ArgumentParser, *, radius_required: bool,
                       radius_default: str) -> None:
    """The z-stack argument and the options :func:`stack_sampling` reads."""
    parser.add_argument("stack", help="z-stack of beads on a coverslip (Z, Y, X): TIFF "
                        "(ImageJ or OME) or OME-Zarr")
    g = parser.add_mutually_exclusive_group(required=radius_required)
    g.add_argument("--psf-radius", type=POSITIVE, help="lateral PSF radius on the widest "
                   f"plane, pixels{radius_default}")
    g.add_argument("--psf-radius-um", type=POSITIVE, help="the same in micrometres")
    parser.add_argument("--pixel-size-nm", type=POSITIVE,
                        help="pixel size (overrides the file's)")
    parser.add_argument("--z-step-nm", type=POSITIVE,
                        help="plane spacing (overrides the file's)")


def bead_diameter_px(args, info) -> float:
    """--bead-diameter-nm in pixels (0 without it), with the image's pixel size."""
    d = getattr(args, "bead_diameter_nm", None)
    if d is None:
        return 0.0
    if not d >= 0:
        raise ValueError(f"--bead-diameter-nm must be >= 0, got {d}.")
    if not info.pixel_size:
        raise ValueError("--bead-diameter-nm needs the pixel size, which the file does not "
                         "give: pass --pixel-size-nm too.")
    return d / 1000.0 / info.pixel_size


def add_radius_and_slice(parser: argparse.ArgumentParser) -> None:
    """--psf-radius / --psf-radius-um (default: measured from the image), --slice,
    --pixel-size-nm and --bead-diameter-nm."""
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--psf-radius", type=POSITIVE,
                   help="PSF radius r in pixels (default: suggested from the image)")
    g.add_argument("--psf-radius-um", type=POSITIVE,
                   help="PSF radius in micrometres (needs the pixel size in the TIFF)")
    parser.add_argument("--slice", type=INDEX, help="slice of a stack to use (from 0)")
    parser.add_argument("--pixel-size-nm", type=POSITIVE,
                        help="pixel size in nanometres (overrides the file's)")
    parser.add_argument("--bead-diameter-nm", type=NON_NEGATIVE,
                        help="bead diameter in nanometres (from the beads' data sheet): "
                             "divided out of the learnt PSFs (needs the pixel size)")
    parser.add_argument("--remove-motion", action="store_true",
                        help="divide a motion blur found in the beads (a smear common to "
                             "all of them) out of the model; use when the sample was still "
                             "(motion blur is always looked for and reported)")


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors: the option and what is wrong, then where to look
    (the usage block would bury the line that matters)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


__all__ = ["COUNT", "FINITE", "INDEX", "NON_NEGATIVE", "POSITIVE", "SCHEDULER_TIMEOUT", "Parser",
           "add_radius_and_slice", "bead_diameter_px", "existing", "image_and_radius",
           "n_psf_choice", "number", "progress_printer", "psf_radius_px"]
