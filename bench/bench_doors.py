"""Bad calls at every door: the command line and the public API, each given wrong values.

Every call runs in a child of a fork server (the imports shared, no thread state
inherited, a time limit each) and ends as:

* ``refused``: the command line exits 2 with one line naming what is wrong; the API
  raises a ValueError or TypeError whose message names the argument;
* ``accepted``: it ran (a bad-looking value that is legal, e.g. a huge threshold that
  finds no bead and says so is ``refused``; a seed of 10^12 is ``accepted``);
* ``TRACEBACK``: an exception escaped the command line, or the API raised anything
  else (a numpy-internal IndexError, an AttributeError: a bug);
* ``UNNAMED``: the API's error does not name the argument;
* ``GARBAGE``: a result holding NaN or infinity;
* ``RUNS ON``: past the time limit (a size that should have been refused).

The CLI's bad values: for every option that takes one, each of ``-1 0 nan inf 1e12
abc ''`` (its own default where the option is a choice), plus missing, damaged (text),
empty and folder inputs and unwritable outputs for each command; the API's: each
public entry's numeric arguments given ``nan, -1, 0, 1e12, 'x', None, [1, 2]`` and its
image given a wrong shape, NaNs, a string.

    python bench/bench_doors.py [--limit 60] [--kills 20]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchlib import table

BAD = ["-1", "0", "nan", "inf", "1e12", "abc", ""]


def _child(conn, kind, payload, cwd):
    """Run one call in ``cwd`` (a bad value taken for a file name lands there); send
    back (outcome, detail)."""
    os.chdir(cwd)
    out, err = io.StringIO(), io.StringIO()
    try:
        if kind == "cli":
            from napari_psfspace.cli import main

            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                rc = main(payload)
            lines = [ln for ln in err.getvalue().splitlines() if "error" in ln]
            if rc == 0:
                res = ("GARBAGE" if " nan" in out.getvalue().lower() else "accepted",
                       out.getvalue()[-120:])
            elif rc == 2 and len(lines) == 1:
                res = ("refused", lines[0][:160])
            else:
                res = ("UNNAMED", f"rc {rc}: {err.getvalue()[-200:]}")
        else:
            func, kwargs, name = payload
            try:
                got = func(**kwargs)
            except (ValueError, TypeError) as exc:
                msg = str(exc)
                named = name is None or name in msg
                res = ("refused" if named else "UNNAMED", msg[:160])
            else:
                arrays = [got] if isinstance(got, np.ndarray) else [
                    v for v in (getattr(got, "__dict__", {}) or {}).values()
                    if isinstance(v, np.ndarray)]
                bad = any(a.dtype.kind == "f" and not np.isfinite(a).all() for a in arrays)
                res = ("GARBAGE" if bad else "accepted", type(got).__name__)
    except BaseException as exc:  # noqa: BLE001  (what escapes is the finding)
        res = ("TRACEBACK", f"{type(exc).__name__}: {str(exc)[:160]}")
    conn.send(res)
    conn.close()


def run(kind, payload, limit: float, cwd: Path):
    # a fork server started before any computation: a child forked from a process whose
    # BLAS and worker threads have run can deadlock (the first run of this bench: 34 legal
    # calls "ran on" past a minute); the server's imports are shared, its threads never ran
    ctx = mp.get_context("forkserver")
    a, b = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(b, kind, payload, str(cwd)))
    proc.start()
    b.close()
    if a.poll(limit):
        res = a.recv()
        proc.join(5)
    else:
        res = ("RUNS ON", f"> {limit:g} s")
    if proc.is_alive():
        proc.kill()
        proc.join()
    return res


def _files(tmp: Path) -> dict:
    """Small valid inputs, and damaged ones."""
    import napari_psfspace as ps
    from napari_psfspace.io import write_tiff

    img, truth = ps.simulate_beads((256, 256), 25, seed=0)
    write_tiff(tmp / "img.tif", img, pixel_size=truth.optics.pixel_size)
    stack, series = ps.simulate_focus_series((192, 192), 6, (-0.4, 0.0, 0.4), seed=0)
    write_tiff(tmp / "stack.tif", stack, pixel_size=series.optics.pixel_size)
    op = ps.estimate_operator(img, psf_radius=truth.psf_radius)
    op.save(tmp / "model.npz")
    (tmp / "text.tif").write_text("not a tiff")
    (tmp / "empty.tif").write_bytes(b"")
    (tmp / "folder.tif").mkdir()
    (tmp / "text.npz").write_text("not a model")
    ro = tmp / "readonly"
    ro.mkdir()
    os.chmod(ro, 0o500)
    return {"img": str(tmp / "img.tif"), "stack": str(tmp / "stack.tif"),
            "model": str(tmp / "model.npz"), "r": str(truth.psf_radius)}


def cli_calls(tmp: Path, f: dict) -> list[list[str]]:
    from napari_psfspace.cli import build_parser

    o = str(tmp / "out")
    base = {
        "simulate": ["simulate", "-o", o + ".tif", "--shape", "64", "64", "--beads", "3"],
        "estimate": ["estimate", f["img"], "-o", o + ".npz", "--psf-radius", f["r"], "-q"],
        "diagnose": ["diagnose", f["img"], "--report", o + "_rep", "--psf-radius", f["r"],
                     "-q"],
        "learn": ["learn", f["stack"], "-o", o + "_fam.npz", "--psf-radius", f["r"], "-q"],
        "psf": ["psf", f["model"], "--at", "10", "10", "-o", o + "_psf.tif"],
        "apply": ["apply", f["model"], f["img"], "-o", o + "_b.tif"],
        "deblur": ["deblur", f["img"], "--model", f["model"], "-o", o + "_d.tif", "-q"],
        "estimate3d": ["estimate3d", f["stack"], "-o", o + "_3d.npz", "--psf-radius",
                       f["r"], "-q"],
        "deblur3d": ["deblur3d", f["stack"], "--model", f["model"], "-o", o + "_d3.tif",
                     "-q"],
    }
    parser = build_parser()
    subs = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    calls = []
    for cmd, argv in base.items():
        sp = subs.choices[cmd]
        for action in sp._actions:
            if not action.option_strings or action.nargs == 0 or action.dest == "help":
                continue
            flag = action.option_strings[-1]
            n = action.nargs if isinstance(action.nargs, int) else 1
            values = ["abc", ""] if action.choices else BAD
            # an output (every command names its own: path_outputs) takes bad paths
            if action.dest in (sp.get_default("path_outputs") or {}):
                values = [str(tmp / "missing" / "x.tif"), str(tmp / "readonly" / "x.tif"),
                          str(tmp / "folder.tif"), ""]
            for v in values:
                rest = list(argv)
                if flag in rest:  # replace the valid value
                    i = rest.index(flag)
                    del rest[i:i + 1 + n]
                calls.append(rest + [flag, *([v] * n)])
        # the positional files: missing, damaged, empty, a folder
        files = [a for a in argv[1:3] if a.endswith((".tif", ".npz")) and not a.startswith(o)]
        for good in files:
            for bad in ("missing.tif", "text.tif", "empty.tif", "folder.tif", "text.npz"):
                calls.append([a if a != good else str(tmp / bad) for a in argv])
    return calls


def api_calls() -> list[tuple]:
    import napari_psfspace as ps

    img, truth = ps.simulate_beads((192, 192), 12, seed=1)
    r = float(truth.psf_radius)
    op = ps.estimate_operator(img, psf_radius=r)
    stack = np.stack([img, img])
    vals = [np.nan, -1, 0, 1e12, "x", None, [1, 2]]
    calls = []

    def each(func, fixed, name, values=vals):
        for v in values:
            calls.append((func, {**fixed, name: v}, f"`{name}`"))

    for name in ("psf_radius", "threshold", "n_psf", "smoothing", "grid_step"):
        each(ps.estimate_operator, {"image": img, "psf_radius": r}, name)
    for name in ("psf_radius", "threshold", "folds", "gain", "read_noise"):
        each(ps.diagnose, {"image": img, "psf_radius": r, "effects": []}, name)
    each(ps.estimate_family, {"images": stack, "psf_radius": r}, "psf_radius")
    each(ps.estimate_family, {"images": stack, "psf_radius": r}, "client",
         ["x", 3, [1]])
    for name in ("n_beads", "seed"):
        each(ps.simulate_beads, {"shape": (64, 64), "n_beads": 3}, name,
             [np.nan, -1, "x", [1, 2]])
    each(ps.simulate_beads, {"n_beads": 3}, "shape",
         [(200000, 200000), (8, 8), (64,), "x", (np.nan, 64)])
    each(ps.suggest_psf_radius, {"image": img}, "n_beads", [-1, 0, "x", np.nan])
    each(op.psf_at, {"y": 10.0}, "x", [np.nan, 1e9, -5, "x", [1, 2]])
    each(op.psf_at, {"x": 10.0}, "y", [np.nan, 1e9, -5, "x"])
    each(ps.deblur, {"image": img, "operator": op}, "max_iter", [-1, 0, np.nan, "x"])
    each(ps.best_focus_index, {}, "stack", [img, "x", np.zeros((3, 4, 4)),
                                            np.full((3, 32, 32), np.nan)])
    zs, _ = ps.simulate_focus_series((128, 128), 4, (-0.4, 0.0, 0.4), seed=0)
    for name in ("psf_radius", "z_radius", "threshold", "grid_step"):
        each(ps.estimate_operator_3d, {"stack": zs, "psf_radius": 10.0}, name,
             [np.nan, -1, 0, 1e12, "x", [1, 2]])
    each(ps.simulate_focus_series, {"shape": (64, 64), "n_beads": 2}, "z_um",
         [[np.nan], [], "x", np.full(100000, 0.1)])
    op3 = ps.estimate_operator_3d(zs, psf_radius=10.0)
    each(ps.richardson_lucy_3d, {"stack": zs, "operator": op3}, "n_iter",
         [-1, 0, np.nan, "x", 2.5])
    each(ps.richardson_lucy_3d, {"operator": op3}, "stack",
         [zs[0], np.full_like(zs, np.nan, dtype=float), "x"])
    for bad_img in (np.zeros(5), np.full((64, 64), np.nan), "x", np.zeros((2, 3, 4, 5)),
                    (img > img.mean()).astype(np.uint8), np.full((64, 64), 7.0)):
        calls.append((ps.estimate_operator, {"image": bad_img, "psf_radius": r}, None))
        calls.append((ps.diagnose, {"image": bad_img, "psf_radius": r}, None))
    return calls


def kills(tmp: Path, n: int) -> int:
    """``n`` writes of a model killed (SIGKILL) while writing; the stale temporary files
    left after one more, ordinary write to the same path."""
    target = tmp / "killed.npz"
    code = ("import sys, time; from napari_psfspace.core.common.atomic import atomic_write; "
            f"atomic_write({str(target)!r}, lambda fh: (fh.write(b'x' * 4096), fh.flush(), "
            "print('in', flush=True), time.sleep(60)))")
    for _ in range(n):
        p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
        p.stdout.readline()
        p.send_signal(signal.SIGKILL)
        p.wait()
    from napari_psfspace.core.common.atomic import atomic_write

    atomic_write(target, lambda fh: fh.write(b"ok"))
    return sum(1 for p in tmp.iterdir() if p.name.endswith(".tmp"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--limit", type=float, default=60.0, help="seconds a call may take")
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--doors", nargs="+", default=["cli", "api"])
    args = ap.parse_args()
    mp.set_forkserver_preload(["napari_psfspace", "napari_psfspace.cli", "bench_doors"])
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        f = _files(tmp)
        (tmp / "cwd").mkdir()
        rows, findings = [], []
        for kind, make in (("cli", lambda: cli_calls(tmp, f)), ("api", api_calls)):
            if kind not in args.doors:
                continue
            calls = make()
            counts: dict[str, int] = {}
            for c in calls:
                res, detail = run(kind, c, args.limit, tmp / "cwd")
                counts[res] = counts.get(res, 0) + 1
                if res not in ("refused", "accepted"):
                    what = " ".join(c) if kind == "cli" else (
                        f"{getattr(c[0], '__name__', c[0])}("
                        f"{', '.join(f'{k}={type(v).__name__}' for k, v in c[1].items())}"
                        f") [{c[2]}]")
                    findings.append(f"{kind} {res}: {what}\n    {detail}")
            rows.append({"door": kind, "calls": len(calls), **counts})
        stale = kills(tmp, args.kills)
        os.chmod(tmp / "readonly", 0o700)
    cols = [("door", "s"), ("calls", "d")] + [
        (k, "d") for k in ("refused", "accepted", "TRACEBACK", "UNNAMED", "GARBAGE",
                           "RUNS ON")]
    print(table(rows, cols))
    print(f"\n{args.kills} writes killed with SIGKILL mid-write: {stale} stale temporary "
          f"file(s) after the next write ({time.perf_counter() - t0:.0f} s in all)")
    for line in findings:
        print(line)


if __name__ == "__main__":
    main()
