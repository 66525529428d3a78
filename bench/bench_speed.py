"""Time and peak memory of estimate_operator on 2304x2304 images (2 cores).

    python bench/bench_speed.py [--repeat N] [--baseline OTHER/src]

With ``--baseline``, each case is also run with the package found in another checkout's
``src`` folder (e.g. ``git worktree add /tmp/base <commit>``), the two interleaved in
fresh processes ``--rounds`` times, so that a change is measured against the drift of
this VM's timings (10-30 % from one run to the next).

Each case runs in a fresh process that loads a pre-simulated image, so the reported peak
memory (ru_maxrss) is that of the estimation alone plus the interpreter and the image.
Targets of the issue: <= 10 s and <= 2 GB with 120-400 beads.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchlib import SRC, table
from napari_psfspace.core.simulation import simulate_beads

CHILD = r"""
import json, resource, sys, time
import numpy as np
sys.path.insert(0, {src!r})
from napari_psfspace.core.model.estimate import iter_estimate
image = np.load({path!r})
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
times = []
for _ in range({repeat}):
    t0 = time.perf_counter(); stages = []; last = t0
    gen = iter_estimate(image, psf_radius={radius})
    try:
        while True:
            p = next(gen); now = time.perf_counter()
            stages.append((p.stage, now - last)); last = now
    except StopIteration as stop:
        est = stop.value
    times.append(time.perf_counter() - t0)
print(json.dumps({{"seconds": sorted(times)[len(times) // 2], "best": min(times),
    "stages": stages, "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    "image_mb": image.nbytes / 2**20, "n_psf": est.operator.n_psf,
    "used": est.operator.metadata["n_beads_used"]}}))
"""


def _run(src: str, path: str, repeat: int, radius: float) -> dict:
    code = CHILD.format(src=src, path=path, repeat=repeat, radius=radius)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--baseline", help="another checkout's src folder to compare with")
    ap.add_argument("--rounds", type=int, default=4,
                    help="interleaved rounds with --baseline (default 4)")
    args = ap.parse_args()
    rows, compared = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for n, preset in [(120, "moderate"), (250, "strong"), (400, "strong")]:
            image, truth = simulate_beads((2304, 2304), n, aberrations=preset, seed=7)
            path = str(Path(tmp) / f"img{n}.npy")
            np.save(path, image)
            r = _run(str(SRC), path, args.repeat, truth.psf_radius)
            stages = ", ".join(f"{s} {t:.2f}" for s, t in r["stages"])
            rows.append({"beads": n, "aberrations": preset, "r": truth.psf_radius,
                         "I": r["n_psf"], "used": r["used"], "median_s": r["seconds"],
                         "best_s": r["best"], "peak_MB": r["maxrss_mb"], "stages": stages})
            if args.baseline:
                runs: dict[str, list] = {"base": [], "this": []}
                for _ in range(args.rounds):
                    for name, src in (("base", args.baseline), ("this", str(SRC))):
                        runs[name].append(_run(src, path, args.repeat, truth.psf_radius))
                med = {k: float(np.median([x["seconds"] for x in v])) for k, v in runs.items()}
                best = {k: min(x["best"] for x in v) for k, v in runs.items()}
                compared.append({"beads": n, "base_median_s": med["base"],
                                 "this_median_s": med["this"],
                                 "change_%": 100 * (med["this"] / med["base"] - 1),
                                 "base_best_s": best["base"], "this_best_s": best["this"]})
    print(f"estimate_operator on 2304x2304 uint16 (median of {args.repeat} runs; holdout on)")
    print(table(rows, [("beads", "d"), ("aberrations", "s"), ("r", "d"), ("I", "d"),
                       ("used", "d"), ("median_s", ".2f"), ("best_s", ".2f"),
                       ("peak_MB", ".0f"), ("stages", "s")]))
    if compared:
        print(f"\nagainst {args.baseline}, {args.rounds} interleaved rounds of {args.repeat} "
              "runs each")
        print(table(compared, [("beads", "d"), ("base_median_s", ".3f"),
                               ("this_median_s", ".3f"), ("change_%", "+.1f"),
                               ("base_best_s", ".3f"), ("this_best_s", ".3f")]))


if __name__ == "__main__":
    main()
