"""One entry point for every benchmark: list them, run one and keep its result as data,
write ``bench/RESULTS.md`` from the results.

    python bench/run.py --list                 # every bench, with what it measures
    python bench/run.py NAME [ARGS...]         # run bench_NAME.py ARGS; save its result
    python bench/run.py NAME --as LABEL ARGS   # the same, kept under NAME.LABEL
    python bench/run.py --render               # bench/RESULTS.md from bench/results/

A run's printed tables (its standard output; progress goes to standard error) are saved
in ``bench/results/NAME[.LABEL].json`` with the command that made them, the commit (and
whether the tree had changes), the machine and the date. ``--render`` writes the current
result of each bench, with its command, into ``bench/RESULTS.md``: history lives in git.
Standard library only: it runs on a bare machine (a GPU's).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
RESULTS_MD = HERE / "RESULTS.md"
#: The result format written (``bench/results/*.json``).
FORMAT = "napari-psfspace/bench-result"
FORMAT_VERSION = 1
#: The first line of a RESULTS.md that --render wrote.
HEADER = "# Benchmark results (generated)"
#: Lines of a result's output shown in RESULTS.md (the rest stays in its JSON file).
SHOWN_LINES = 24


def benches() -> dict[str, str]:
    """Every bench: its name (``bench_NAME.py``) and the first line of its docstring."""
    out = {}
    for path in sorted(HERE.glob("bench_*.py")):
        name = path.stem[len("bench_"):]
        out[name] = _first_line(path)
    return out


def _first_line(path: Path) -> str:
    import ast

    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    return " ".join(doc.split("\n\n")[0].split())


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def machine() -> dict:
    """What the figures were measured on."""
    info = {"node": platform.node(), "system": platform.system(),
            "machine": platform.machine(), "python": platform.python_version(),
            "cores": os.cpu_count()}
    try:
        with open("/proc/meminfo") as f:
            kb = int(next(line for line in f if line.startswith("MemTotal:")).split()[1])
        info["memory_GiB"] = round(kb / 2**20, 1)
    except (OSError, StopIteration, ValueError):
        pass
    try:
        with open("/proc/cpuinfo") as f:
            info["cpu"] = next(line.split(":", 1)[1].strip() for line in f
                               if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    gpu = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total", "--format=csv,noheader"],
                         capture_output=True, text=True) if _which("nvidia-smi") else None
    info["gpu"] = gpu.stdout.strip() if gpu is not None and gpu.returncode == 0 else None
    return info


def _which(cmd: str) -> bool:
    from shutil import which

    return which(cmd) is not None


def run(name: str, args: list[str], label: str | None = None) -> Path:
    """Run ``bench_NAME.py ARGS`` from ``bench/`` (its output shown as it comes), save the
    result; returns the JSON file's path. A bench that fails saves nothing."""
    script = HERE / f"bench_{name}.py"
    if not script.exists():
        raise SystemExit(f"run.py: no bench {name!r} (bench/bench_{name}.py); "
                         f"`python bench/run.py --list` names them")
    command = " ".join(["python bench/run.py", name, *(["--as", label] if label else []),
                        *args])
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, script.name, *args], cwd=HERE,
                            stdout=subprocess.PIPE, text=True)
    lines = []
    assert proc.stdout is not None
    for line in proc.stdout:
        sys.stdout.write(line)
        sys.stdout.flush()
        lines.append(line)
    code = proc.wait()
    if code != 0:
        raise SystemExit(f"run.py: bench_{name}.py exited with status {code}: no result "
                         "saved")
    result = {"format": FORMAT, "version": FORMAT_VERSION, "bench": name, "label": label,
              "what": _first_line(script), "command": command, "args": args,
              "commit": _git("rev-parse", "HEAD"),
              "tree_changed": bool(_git("status", "--porcelain", "--untracked-files=no")),
              "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "machine": machine(), "seconds": round(time.perf_counter() - t0, 1),
              "output": "".join(lines)}
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}{'.' + label if label else ''}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    tmp.replace(path)
    print(f"\nrun.py: saved {path.relative_to(ROOT)}", file=sys.stderr)
    return path


def load_results() -> list[dict]:
    out = []
    for path in sorted(RESULTS.glob("*.json")):
        data = json.loads(path.read_text(encoding="utf-8"))
        if data.get("format") != FORMAT:
            raise SystemExit(f"run.py: {path} is not a bench result")
        data["file"] = (str(path.relative_to(ROOT)) if path.is_relative_to(ROOT)
                        else str(path))
        out.append(data)
    return out


def render(results: list[dict], names: dict[str, str]) -> str:
    """RESULTS.md: the current result of each bench, with its command."""
    lines = [HEADER, "",
             "Generated by `python bench/run.py --render` from `bench/results/*.json`; each "
             "figure comes with the command that reproduces it, the commit and the machine. "
             "Earlier figures and the notes that went with them are in git's history of this "
             "file. Benches without a result here have not been run since results became "
             "data.", ""]
    by_bench: dict[str, list[dict]] = {}
    for r in results:
        by_bench.setdefault(r["bench"], []).append(r)
    for name in sorted(by_bench):
        for r in sorted(by_bench[name], key=lambda r: r.get("label") or ""):
            m = r["machine"]
            where = (f"{m.get('cores')} cores, {m.get('memory_GiB', '?')} GiB"
                     + (f", {m['gpu']}" if m.get("gpu") else ", no GPU"))
            head = f"## {name}" + (f" ({r['label']})" if r.get("label") else "")
            out = r["output"].rstrip("\n").splitlines()
            shown = out[-SHOWN_LINES:]
            lines += [head, "", r.get("what") or names.get(name, ""), "",
                      f"`{r['command']}`: commit {r['commit'][:10]}"
                      + (" (with changes)" if r.get("tree_changed") else "")
                      + f", {r['date'][:10]}, {where}, {r['seconds']:.0f} s", "", "```"]
            if len(out) > len(shown):
                lines.append(f"... ({len(out) - len(shown)} lines before: {r['file']})")
            lines += shown + ["```", ""]
    missing = sorted(set(names) - set(by_bench))
    if missing:
        lines += ["## Not yet run as data", "", ", ".join(missing), ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 usage="%(prog)s [--list | --render | NAME [--as LABEL] "
                                       "[ARGS...]]")
    ap.add_argument("--list", action="store_true", help="name every bench")
    ap.add_argument("--render", action="store_true", help="write bench/RESULTS.md")
    ap.add_argument("--out", type=Path, default=RESULTS_MD,
                    help="with --render: the file written (default bench/RESULTS.md)")
    ap.add_argument("--force", action="store_true",
                    help="with --render: replace a RESULTS.md written by hand")
    ap.add_argument("--as", dest="label", help="keep the result under NAME.LABEL")
    ap.add_argument("name", nargs="?", help="the bench (bench_NAME.py)")
    args, rest = ap.parse_known_args()
    names = benches()
    if args.list:
        width = max(map(len, names))
        for name, what in names.items():
            print(f"{name.ljust(width)}  {what}")
        return
    if args.render:
        out = args.out.resolve()
        if out.exists() and not args.force and not out.read_text(
                encoding="utf-8").startswith(HEADER):
            raise SystemExit(f"run.py: {out} was not written by --render (its figures "
                             "would be lost): give --out elsewhere, or --force")
        text = render(load_results(), names)
        out.write_text(text + "\n", encoding="utf-8")
        print(f"wrote {out}: {len(text.splitlines())} lines")
        return
    if not args.name:
        ap.error("give a bench's NAME, --list or --render")
    run(args.name, rest, args.label)


if __name__ == "__main__":
    main()
