"""Write ``tests/slow_tests.txt`` from a pytest run's durations: every test that took at
least ``--min`` seconds (in its call or its setup) is marked ``slow`` by
``tests/conftest.py``, and ``make check`` leaves it out.

    python -m pytest --durations=0 --durations-min=1 > durations.log
    python tests/update_slow.py durations.log [--min 1]
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

LINE = re.compile(r"^(\d+(?:\.\d+)?)s (call|setup|teardown)\s+(\S+)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path, help="pytest's output with --durations=0")
    ap.add_argument("--min", type=float, default=1.0, help="seconds (default 1)")
    args = ap.parse_args()
    seconds: dict[str, float] = {}
    for line in args.log.read_text(encoding="utf-8").splitlines():
        m = LINE.match(line.strip())
        if m:
            node = m.group(3)
            seconds[node] = seconds.get(node, 0.0) + float(m.group(1))
    slow = sorted((n for n, s in seconds.items() if s >= args.min), key=lambda n: -seconds[n])
    out = Path(__file__).with_name("slow_tests.txt")
    out.write_text("# Tests marked slow (tests/conftest.py): at least "
                   f"{args.min:g} s in their call or setup.\n"
                   "# Made by `python tests/update_slow.py LOG` (see its docstring).\n"
                   + "".join(f"{seconds[n]:7.2f} {n}\n" for n in slow), encoding="utf-8")
    print(f"wrote {out}: {len(slow)} tests")


if __name__ == "__main__":
    main()
