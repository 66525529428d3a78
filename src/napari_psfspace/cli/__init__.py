"""Command line: ``psfspace simulate | estimate | diagnose | learn | psf | apply | deblur |
estimate3d | deblur3d | qc | demo``.

Run ``psfspace COMMAND --help`` for the options of each command. Errors in the input
(no beads, a stack without a slice, a model for another image size...) end with a
one-line message and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import sys

from ..core.common.version import package_version
from . import (
    apply,
    deblur,
    deblur3d,
    demo,
    diagnose,
    estimate,
    estimate3d,
    learn,
    psf,
    qc,
    simulate,
)
from .common import Parser

#: The commands, in the order ``psfspace --help`` lists them.
COMMANDS = (simulate, estimate, diagnose, learn, psf, apply, deblur, estimate3d, deblur3d, qc,
            demo)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="psfspace",
        description="Learn space-varying PSF operators from images of fluorescent beads.",
    )
    p.add_argument("--version", action="version", version=f"napari-psfspace {package_version()}")
    sub = p.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def _check_paths(args) -> None:
    """No output path of the command is one of its inputs or another of its outputs
    (each command names its path arguments: ``set_defaults(path_inputs=..., path_outputs=...)``,
    ``{dest: option as the user reads it}``)."""
    from ..io import check_distinct

    def named(kind: str) -> dict:
        return {option: getattr(args, dest, None)
                for dest, option in (getattr(args, kind, None) or {}).items()}

    check_distinct(named("path_outputs"), named("path_inputs"))


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``psfspace``; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a bad option (said in one line)
        return exc.code if isinstance(exc.code, int) else 2
    try:
        _check_paths(args)
        return args.func(args)
    except FileNotFoundError as exc:
        print(f"psfspace {args.command}: error: {exc.filename}: no such file", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        msg = " ".join(str(exc).split())  # one line
        print(f"psfspace {args.command}: error: {msg}", file=sys.stderr)
        return 2


__all__ = ["COMMANDS", "build_parser", "main"]
