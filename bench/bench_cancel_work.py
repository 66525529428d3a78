"""How long a step keeps working after Cancel: the process's CPU, measured from the
moment the panel's Cancel is pressed until the process is idle again.

    python bench/bench_cancel_work.py [--at 2 5 8 12 20 30 45 60] [--image sp8|stars|both]
        [--baseline SRC]

Diagnose (the panel's step that runs longest between two of its records) runs as the
panel runs it: its core generator driven through
:func:`~napari_psfspace.core.common.progress.responsive` by a consumer thread, which
stops asking for records ``--at`` seconds after the start (Cancel). From then on the
process's CPU time is sampled every 0.1 s; ``busy_s`` is the time from Cancel to the end
of the last 0.1 s window in which the process used more than a tenth of a core (before
three idle windows in a row), ``cpu_s`` the CPU seconds it spent in that time. Images:
the best-focus slice of the SP8 confocal stack (1024 x 1024, radius 12 px) and the star
field (2048 x 3072, radius 8 px). ``--baseline SRC``: the same with another checkout's
``src`` (the code before a change) in a subprocess, side by side.

Needs ``../shared/data``; run it on a quiet machine (the figures are seconds).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from benchlib import table

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SP8 = DATA / "sp8_confocal_beads" / "sp8_series045_beads_zyx_uint8.tif"
STARS = DATA / "starfield_2d" / "dash_starfield_uint16.tif"
#: Seconds of a sampling window, the CPU share (cores) above which a window is busy, and
#: the idle windows in a row that end the measurement.
WINDOW, BUSY, IDLE_WINDOWS = 0.1, 0.1, 3


def images(which: str) -> dict[str, tuple[np.ndarray, float]]:
    from napari_psfspace.io import read_image, read_stack

    out = {}
    if which in ("sp8", "both"):
        stack, _ = read_stack(str(SP8))
        focus = int(np.argmax([np.percentile(p, 99.9) for p in stack]))
        out[f"SP8 slice {focus}"] = (stack[focus].astype(np.float32), 12.0)
    if which in ("stars", "both") and STARS.exists():
        out["star field"] = (read_image(str(STARS))[0].astype(np.float32), 8.0)
    return out


def after_cancel(image: np.ndarray, radius: float, at: float) -> dict:
    """Run Diagnose as the panel does, Cancel after ``at`` s; the work after it."""
    from napari_psfspace.core.common.progress import responsive
    from napari_psfspace.core.diagnosis.loop import iter_diagnose

    stop, ended, last = threading.Event(), threading.Event(), {"stage": "start"}

    def consumer():
        gen = responsive(iter_diagnose(image, psf_radius=radius))
        try:
            for rec in gen:
                last["stage"] = rec.stage
                if stop.is_set():
                    break
        finally:
            gen.close()
            ended.set()

    t0 = time.perf_counter()
    threading.Thread(target=consumer, daemon=True).start()
    while time.perf_counter() - t0 < at and not ended.is_set():
        time.sleep(0.01)
    finished_first = ended.is_set()
    stop.set()
    cancel_t, cancel_cpu = time.perf_counter(), time.process_time()
    ended.wait(30)
    answered = time.perf_counter() - cancel_t
    busy_until, idle, cpu_prev = 0.0, 0, cancel_cpu
    while idle < IDLE_WINDOWS and time.perf_counter() - cancel_t < 300:
        time.sleep(WINDOW)
        cpu = time.process_time()
        share = (cpu - cpu_prev) / WINDOW
        cpu_prev = cpu
        if share > BUSY:
            busy_until, idle = time.perf_counter() - cancel_t, 0
        else:
            idle += 1
    cpu_s = cpu_prev - cancel_cpu
    return {"at_s": at, "stage": last["stage"], "answered_s": answered,
            "busy_s": busy_until, "cpu_s": cpu_s, "finished_first": finished_first}


def measure(which: str, ats: list[float]) -> list[dict]:
    rows = []
    for name, (image, radius) in images(which).items():
        for at in ats:
            row = after_cancel(image, radius, at)
            rows.append({"image": name, **row})
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
            time.sleep(1.0)  # the next run starts on an idle process
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--at", type=float, nargs="+", default=[2, 5, 8, 12, 20, 30, 45, 60],
                    help="seconds after the start at which Cancel is pressed")
    ap.add_argument("--image", choices=("sp8", "stars", "both"), default="both")
    ap.add_argument("--baseline", default=None,
                    help="another checkout's src: the same in a subprocess, beside")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if not SP8.exists():
        raise SystemExit(f"needs {SP8}")
    rows = measure(args.image, args.at)
    if args.json:
        print(json.dumps(rows))
        return
    for r in rows:
        r["code"] = "this checkout"
    if args.baseline:
        env = {**os.environ, "PYTHONPATH": str(Path(args.baseline).resolve())}
        cmd = [sys.executable, __file__, "--json", "--image", args.image,
               "--at", *map(str, args.at)]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        base = json.loads(out.stdout.strip().splitlines()[-1])
        rows += [{**r, "code": f"baseline {args.baseline}"} for r in base]
    rows = [r for r in rows if not r["finished_first"]]
    print("Diagnose cancelled at_s after its start, as the panel runs it: the stage under "
          "way, seconds until the panel's wait ended, until the process was idle again, "
          "and the CPU seconds spent after Cancel")
    print(table(rows, [("code", "s"), ("image", "s"), ("at_s", ".0f"), ("stage", "s"),
                       ("answered_s", ".2f"), ("busy_s", ".2f"), ("cpu_s", ".2f")]))
    for code in dict.fromkeys(r["code"] for r in rows):
        sel = [r for r in rows if r["code"] == code]
        worst = max(sel, key=lambda r: r["busy_s"])
        print(f"{code}: the longest work after Cancel {worst['busy_s']:.2f} s "
              f"({worst['image']}, Cancel at {worst['at_s']:.0f} s, {worst['stage']}); "
              f"CPU after Cancel at most {max(r['cpu_s'] for r in sel):.2f} s")


if __name__ == "__main__":
    main()
