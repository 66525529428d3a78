"""``psfspace demo``."""

from __future__ import annotations

import json

from .common import INDEX, progress_printer


def run(args) -> int:
    from ..demo import format_table, run_demo
    from ..io import check_output_folder

    check_output_folder(args.out, "--out")
    result = run_demo(args.out, scene=args.scene, seed=args.seed,
                      progress=None if args.quiet else progress_printer())
    print(format_table(result))
    print(f"\nfigures, TIFFs, model and errors.json in {args.out}/")
    if args.json:
        print(json.dumps(result["errors"], indent=2))
    return 0


def add_parser(sub) -> None:
    d = sub.add_parser("demo", help="simulate a wide field, estimate, report errors, draw")
    d.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    d.add_argument("--scene", choices=("wide", "moderate", "small"), default="wide",
                   help="wide: 2048x2048, 400 beads, strong aberrations (default)")
    d.add_argument("--seed", type=INDEX, default=0)
    d.add_argument("--json", action="store_true", help="also print the errors as JSON")
    d.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    d.set_defaults(func=run, path_inputs={},
                   path_outputs={"out": "--out"})
