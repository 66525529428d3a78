"""Time of ``diagnose`` on the power bench's scenes, against another checkout.

    python bench/bench_diagnose_speed.py --baseline OTHER/src [--seeds 20 21 22 23]
        [--cases none "hot pixels" "companions 1-3 px"] [--rounds 2]

Each scene (``bench_power.py``'s setting: 1024 x 1024, 150 beads) is simulated once and
saved; each ``diagnose`` then runs in a fresh process with the package of this checkout
or of ``--baseline`` (e.g. ``git worktree add /tmp/base <commit>``, then
``/tmp/base/src``), the two interleaved ``--rounds`` times, so that a change is measured
against the drift of the machine's timings. ``OPENBLAS_NUM_THREADS=1`` is advised on a
shared machine. Prints each scene's median time for both and their ratio.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench_power import CASES, SETTING
from benchlib import SRC, table
from napari_psfspace.core.simulation.scene_set import random_scene

CHILD = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, {src!r})
from napari_psfspace.core.diagnosis.loop import diagnose
image = np.load({path!r})
t0 = time.perf_counter()
d = diagnose(image, psf_radius={radius})
print(json.dumps({{"seconds": time.perf_counter() - t0, "added": d.added}}))
"""


def _run(src: str, path: str, radius: float) -> dict:
    code = CHILD.format(src=src, path=path, radius=radius)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", required=True, help="another checkout's src folder")
    ap.add_argument("--seeds", type=int, nargs="+", default=[20, 21, 22, 23])
    ap.add_argument("--cases", nargs="+", default=["none", "hot pixels", "companions 1-3 px"])
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.cases:
            _, strengths, _, make = CASES[case]
            for seed in args.seeds:
                image, truth, _ = random_scene(seed, effects=make(strengths[0], seed),
                                               **SETTING)
                path = str(Path(tmp) / f"scene{seed}.npy")
                np.save(path, image)
                runs: dict[str, list] = {"base": [], "this": []}
                try:
                    for _ in range(args.rounds):
                        for name, src in (("base", args.baseline), ("this", str(SRC))):
                            runs[name].append(_run(src, path, truth.psf_radius))
                except subprocess.CalledProcessError:  # refused (too few usable beads)
                    continue
                med = {k: float(np.median([r["seconds"] for r in v])) for k, v in runs.items()}
                rows.append({"case": case, "seed": seed, "base_s": med["base"],
                             "this_s": med["this"], "ratio": med["this"] / med["base"],
                             "added_base": ", ".join(runs["base"][0]["added"]) or "-",
                             "added_this": ", ".join(runs["this"][0]["added"]) or "-"})
                print(rows[-1], file=sys.stderr, flush=True)
    print(f"diagnose against {args.baseline}, median of {args.rounds} interleaved runs")
    print(table(rows, [("case", "s"), ("seed", "d"), ("base_s", ".1f"), ("this_s", ".1f"),
                       ("ratio", ".2f"), ("added_base", "s"), ("added_this", "s")]))
    if rows:
        print(f"\nlargest ratio {max(r['ratio'] for r in rows):.2f}, median "
              f"{float(np.median([r['ratio'] for r in rows])):.2f}")


if __name__ == "__main__":
    main()
