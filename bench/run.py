"""One entry point for every benchmark: list them, run one and keep its result as data,
write ``bench/RESULTS.md`` from the results.

    python bench/run.py --list                 # every bench, with what it measures
    python bench/run.py NAME [ARGS...]         # run bench_NAME.py ARGS; save its result
    python bench/run.py NAME --as LABEL ARGS   # the same, kept under NAME.LABEL
    python bench/run.py NAME --scratch ARGS    # run it, save nothing (a tree with changes)
    python bench/run.py --all [--missing]      # every run of bench/suite.txt
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
#: The command of each bench whose result RESULTS.md shows (``--all`` runs them).
SUITE = HERE / "suite.txt"
#: The result format written (``bench/results/*.json``).
FORMAT = "napari-psfspace/bench-result"
FORMAT_VERSION = 1
#: The first line of a RESULTS.md that --render wrote.
HEADER = "# Benchmark results (generated)"


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


def tree_changed_beside_results(status: str | None = None) -> bool:
    """Whether a tracked file differs from the commit, the runner's own outputs
    (``bench/results/``, ``bench/RESULTS.md``) aside: a run that saved a result leaves
    them changed, and they change no bench's code. ``status``: ``git status
    --porcelain`` output (default: the repository's, tracked files only)."""
    if status is None:
        status = _git("status", "--porcelain", "--untracked-files=no")
    own = ("bench/results/", "bench/RESULTS.md")
    # "XY PATH" lines; the first one's leading blank may be stripped with the output's
    paths = [line.split(maxsplit=1)[1].split(" -> ")[-1].strip('"')
             for line in status.splitlines() if len(line.split(maxsplit=1)) == 2]
    return any(not p.startswith(own) for p in paths)


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


def run(name: str, args: list[str], label: str | None = None, table: int | None = None,
        *, scratch: bool = False) -> Path | None:
    """Run ``bench_NAME.py ARGS`` from ``bench/`` (its output shown as it comes), save the
    result; returns the JSON file's path. A bench that fails saves nothing. ``table``:
    the printed table RESULTS.md shows (1: the first; default: the last). A result is
    recorded only from a committed tree (the runner's own outputs aside): with changes,
    the run is refused before it starts, unless ``scratch`` (run it, save nothing)."""
    script = HERE / f"bench_{name}.py"
    if not script.exists():
        raise SystemExit(f"run.py: no bench {name!r} (bench/bench_{name}.py); "
                         f"`python bench/run.py --list` names them")
    command = " ".join(["python bench/run.py", name, *(["--as", label] if label else []),
                        *(["--table", str(table)] if table is not None else []), *args])
    commit = _git("rev-parse", "HEAD")  # what runs: the tree as it is when the bench starts
    tree_changed = tree_changed_beside_results()
    if tree_changed and not scratch:
        raise SystemExit("run.py: tracked files differ from the commit (git status): a "
                         "result is recorded only from a committed tree. Commit first, or "
                         "give --scratch to run it without saving.")
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
    if scratch:
        print("\nrun.py: --scratch: no result saved", file=sys.stderr)
        return None
    result = {"format": FORMAT, "version": FORMAT_VERSION, "bench": name, "label": label,
              "what": _first_line(script), "command": command, "args": args,
              "commit": commit, "tree_changed": tree_changed,
              "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "machine": machine(), "seconds": round(time.perf_counter() - t0, 1),
              "table": table,
              "output": "".join(lines)}
    RESULTS.mkdir(exist_ok=True)
    path = _result_path(name, label)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    tmp.replace(path)
    print(f"\nrun.py: saved {path.relative_to(ROOT)}", file=sys.stderr)
    return path


def suite(path: Path = SUITE) -> list[dict]:
    """The runs of ``bench/suite.txt``: one per line, ``[timed] NAME [--as LABEL] ARGS``
    (``timed``: its figures are seconds, to be run on a quiet machine); ``#`` comments."""
    import shlex

    out = []
    for number, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        words = shlex.split(raw, comments=True)
        if not words:
            continue
        timed = words[0] == "timed"
        words = words[1:] if timed else words
        name, rest, label = words[0], words[1:], None
        table = None
        while rest[:1] in (["--as"], ["--table"]):
            if len(rest) < 2:
                raise SystemExit(f"run.py: {path.name}:{number}: {rest[0]} needs a value")
            if rest[0] == "--as":
                label = rest[1]
            else:
                table = int(rest[1])
            rest = rest[2:]
        out.append({"name": name, "label": label, "table": table, "args": rest,
                    "timed": timed, "line": number})
    return out


def _result_path(name: str, label: str | None) -> Path:
    return RESULTS / f"{name}{'.' + label if label else ''}.json"


def run_all(*, missing: bool = False, timed: bool | None = None) -> None:
    """Run every line of the suite in order (``missing``: those without a result;
    ``timed``: only the timed ones, or only the others); a bench that fails is named at
    the end and the others still run."""
    names = benches()
    failed = []
    for entry in suite():
        if entry["name"] not in names:
            raise SystemExit(f"run.py: suite.txt:{entry['line']}: no bench "
                             f"{entry['name']!r}")
        if missing and _result_path(entry["name"], entry["label"]).exists():
            continue
        if timed is not None and entry["timed"] != timed:
            continue
        print(f"run.py: {entry['name']} {' '.join(entry['args'])}", file=sys.stderr,
              flush=True)
        try:
            run(entry["name"], entry["args"], entry["label"], entry["table"])
        except SystemExit as exc:
            print(exc, file=sys.stderr)
            failed.append(entry["name"])
    if failed:
        raise SystemExit(f"run.py: failed: {', '.join(failed)}")


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


#: The most lines RESULTS.md may have (issue 49); the shown outputs share what is left.
MAX_LINES = 600
#: The most lines of one result's output shown.
SHOWN_LINES = 24


def _blocks(output: str) -> list[list[str]]:
    """A bench's printed output in blocks (its tables): runs of lines between blank
    lines; a block of one line (a note under a table) joins the block before it."""
    blocks: list[list[str]] = [[]]
    for line in output.splitlines():
        if line.strip():
            blocks[-1].append(line)
        elif blocks[-1]:
            blocks.append([])
    blocks = [b for b in blocks if b]
    merged: list[list[str]] = []
    for b in blocks:
        if merged and len(b) == 1:
            merged[-1] = merged[-1] + b
        else:
            merged.append(b)
    return merged or [[]]


def _shown_table(result: dict) -> list[str]:
    """The table of a result that RESULTS.md shows: its ``table`` (1: the first), or
    the last one."""
    blocks = _blocks(result["output"])
    k = result.get("table")
    return blocks[min(k, len(blocks)) - 1] if k else blocks[-1]


def _entries(results: list[dict]) -> list[dict]:
    by_bench: dict[str, list[dict]] = {}
    for r in results:
        by_bench.setdefault(r["bench"], []).append(r)
    return [r for name in sorted(by_bench)
            for r in sorted(by_bench[name], key=lambda r: r.get("label") or "")]


def _budget(blocks: list[list[str]], room: int) -> int:
    """The most lines of each block shown, so that all of them fit in ``room`` lines (a
    cut block gives one line to say where the rest is)."""
    def used(k: int) -> int:
        return sum(len(b) if len(b) <= k else k + 1 for b in blocks)

    k = SHOWN_LINES
    while k > 1 and used(k) > room:
        k -= 1
    return k


def render(results: list[dict], names: dict[str, str]) -> str:
    """RESULTS.md: the current result of each bench (the last table it printed), with its
    command, in at most :data:`MAX_LINES` lines."""
    head = [HEADER, "",
            "Generated by `python bench/run.py --render` from `bench/results/*.json`: for each "
            "bench, a table of its current result (its last, unless the run names one) and "
            "the command that reproduces it (`python bench/run.py --all` runs every command "
            "of `bench/suite.txt`). A "
            "result's whole output is in its JSON file. Earlier figures, and the notes that "
            "went with them, are in git's history of this file.", ""]
    entries = _entries(results)
    missing = sorted(set(names) - {r["bench"] for r in entries})
    tail = (["## Not yet run as data", "", ", ".join(missing)] if missing else [])
    blocks = [_shown_table(r) for r in entries]
    room = MAX_LINES - len(head) - len(tail) - 3 * len(entries) - 1
    k = _budget(blocks, room)
    lines = list(head)
    for r, block in zip(entries, blocks, strict=True):
        m = r["machine"]
        where = (f"{m.get('cores')} cores, {m.get('memory_GiB', '?')} GiB"
                 + (f", {m['gpu']}" if m.get("gpu") else ", no GPU"))
        lines.append(f"## {r['bench']}" + (f" ({r['label']})" if r.get("label") else ""))
        lines.append(f"{r.get('what') or names.get(r['bench'], '')} "
                     f"`{r['command']}`: commit {r['commit'][:10]}"
                     + (" (with changes)" if r.get("tree_changed") else "")
                     + f", {r['date'][:10]}, {where}, {r['seconds']:.0f} s.")
        shown = block if len(block) <= k else block[:k]
        lines += ["    " + line for line in shown]
        if len(block) > k:
            lines.append(f"    ... ({len(block) - k} more lines: {r['file']})")
        lines.append("")
    lines += tail
    return "\n".join(lines).rstrip("\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 usage="%(prog)s [--list | --render | --all [--missing] "
                                       "[--timed only|no] | NAME [--as LABEL] [--scratch] "
                                       "[ARGS...]]")
    ap.add_argument("--list", action="store_true", help="name every bench")
    ap.add_argument("--render", action="store_true", help="write bench/RESULTS.md")
    ap.add_argument("--out", type=Path, default=RESULTS_MD,
                    help="with --render: the file written (default bench/RESULTS.md)")
    ap.add_argument("--force", action="store_true",
                    help="with --render: replace a RESULTS.md written by hand")
    ap.add_argument("--all", action="store_true",
                    help="run every bench of bench/suite.txt with its arguments")
    ap.add_argument("--missing", action="store_true",
                    help="with --all: only those without a result")
    ap.add_argument("--timed", choices=("only", "no"),
                    help="with --all: only the timed runs (a quiet machine), or none")
    ap.add_argument("--table", type=int, help="the printed table RESULTS.md shows (1: the "
                    "first; default: the last)")
    ap.add_argument("--as", dest="label", help="keep the result under NAME.LABEL")
    ap.add_argument("--scratch", action="store_true",
                    help="run NAME and print its tables without saving a result (the only "
                         "way to run it from a tree with changes)")
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
    if args.all:
        run_all(missing=args.missing,
                timed=None if args.timed is None else args.timed == "only")
        return
    if not args.name:
        ap.error("give a bench's NAME, --list or --render")
    run(args.name, rest, args.label, args.table, scratch=args.scratch)


if __name__ == "__main__":
    main()
