"""``bench/run.py``: it names every bench, keeps a run's result as data, and writes
RESULTS.md from the results (without losing a hand-written one)."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _runner():
    spec = importlib.util.spec_from_file_location("bench_run", ROOT / "bench" / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_list_names_every_bench():
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "run.py"), "--list"],
                         capture_output=True, text=True, check=True).stdout
    listed = {line.split()[0] for line in out.splitlines() if line.strip()}
    scripts = {p.stem[len("bench_"):] for p in (ROOT / "bench").glob("bench_*.py")}
    assert listed == scripts and len(scripts) > 30
    # each with what it measures (its docstring's first sentence)
    assert all(len(line.split(None, 1)) == 2 for line in out.splitlines() if line.strip())


def test_render_shows_each_result_with_its_command(tmp_path, monkeypatch):
    run = _runner()
    monkeypatch.setattr(run, "RESULTS", tmp_path)
    result = {"format": run.FORMAT, "version": 1, "bench": "gpu", "label": "smoke",
              "what": "The deblurring on the GPU.", "command": "python bench/run.py gpu "
              "--as smoke --small", "args": ["--small"], "commit": "0123456789abcdef",
              "tree_changed": False, "date": "2026-11-28T00:00:00+00:00",
              "machine": {"cores": 2, "memory_GiB": 24.0, "gpu": None}, "seconds": 12.0,
              "output": "first table\nits rows\n\nlast table\n"
              + "\n".join(f"row {i}" for i in range(40)) + "\n"}
    (tmp_path / "gpu.smoke.json").write_text(json.dumps(result))
    text = run.render(run.load_results(), run.benches())
    assert text.startswith(run.HEADER)
    assert "## gpu (smoke)" in text and "`python bench/run.py gpu --as smoke --small`" in text
    assert "commit 0123456789" in text and "2 cores, 24.0 GiB, no GPU" in text
    # the last table of the output, as much of it as fits, and where the rest is
    assert "    last table" in text and "    row 0" in text and "first table" not in text
    assert "row 39" not in text and "more lines: " in text
    assert "## Not yet run as data" in text  # the other benches, named


def test_render_keeps_a_hand_written_results_file(tmp_path):
    hand = tmp_path / "RESULTS.md"
    hand.write_text("# Results\n\nfigures by hand\n")
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "run.py"), "--render",
                           "--out", str(hand)], capture_output=True, text=True)
    assert done.returncode != 0 and "--force" in done.stderr
    assert hand.read_text() == "# Results\n\nfigures by hand\n"


def test_many_results_fit_in_the_line_budget(tmp_path, monkeypatch):
    """Every bench's result, each with a long last table: RESULTS.md stays within
    MAX_LINES and shows a few lines of each."""
    run = _runner()
    monkeypatch.setattr(run, "RESULTS", tmp_path)
    names = run.benches()
    for name in names:
        result = {"format": run.FORMAT, "version": 1, "bench": name, "label": None,
                  "what": "what it measures.", "command": f"python bench/run.py {name}",
                  "args": [], "commit": "0123456789abcdef", "tree_changed": False,
                  "date": "2026-11-28T00:00:00+00:00", "machine": {"cores": 2},
                  "seconds": 1.0,
                  "output": "\n".join(f"{name} row {i}" for i in range(50)) + "\n"}
        (tmp_path / f"{name}.json").write_text(json.dumps(result))
    text = run.render(run.load_results(), names)
    assert len(text.splitlines()) <= run.MAX_LINES
    assert "Not yet run" not in text
    for name in names:
        assert f"    {name} row 2\n" in text and f"{name} row 49" not in text


def test_results_md_is_the_render_of_the_results():
    """bench/RESULTS.md is what ``run.py --render`` writes from bench/results (rendered
    again after every new result), within its line budget."""
    run = _runner()
    text = (ROOT / "bench" / "RESULTS.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= run.MAX_LINES
    assert text == run.render(run.load_results(), run.benches()) + "\n", (
        "bench/RESULTS.md is stale: run `python bench/run.py --render`")


def test_the_docs_cite_the_figures_of_the_results():
    """Each paragraph of docs/benchmarks.md names the benches it cites (``bench/run.py
    NAME``), and every decimal figure in it is printed in one of their results: the
    page cannot drift from the results."""
    import re

    run = _runner()
    outputs: dict[str, str] = {}
    for r in run.load_results():
        outputs[r["bench"]] = outputs.get(r["bench"], "") + r["output"]
    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    cited = 0
    for block in re.split(r"\n(?=- )|\n\n", text):
        names = re.findall(r"bench/run\.py\s+(\w+)", block)
        figures = re.findall(r"(?<![\w.])\d+\.\d+(?![\w.])", block)
        if not figures:
            continue
        assert names, f"figures without the command that prints them: {block[:80]!r}"
        printed = "".join(outputs.get(n, "") for n in names)
        missing = [f for f in figures if f not in printed]
        assert not missing, (names, missing)
        cited += len(figures)
    assert cited >= 20


def test_a_run_may_name_the_table_shown():
    """``--table K`` (in suite.txt too): the K-th printed table, a note under a table
    staying with it; without it, the last."""
    run = _runner()
    output = "first | table\n1 | 2\n\nnote\n\nlast\n3\n"
    assert run._shown_table({"output": output, "table": 1}) == [
        "first | table", "1 | 2", "note"]
    assert run._shown_table({"output": output}) == ["last", "3"]
    assert run._shown_table({"output": output, "table": 9}) == ["last", "3"]
    entries = {e["name"]: e for e in run.suite()}
    assert entries["accuracy"]["table"] == 1 and "--table" not in entries["accuracy"]["args"]


def test_a_result_saved_before_leaves_the_tree_unchanged():
    """The runner's own outputs (results, RESULTS.md) do not mark a run "with changes";
    any other tracked file does, renamed ones by their new path."""
    run = _runner()
    assert not run.tree_changed_beside_results("")
    assert not run.tree_changed_beside_results(
        " M bench/results/identify.json\n M bench/RESULTS.md\n")
    # as the runner reads it: git's output stripped, the first line's blank with it
    assert not run.tree_changed_beside_results(
        "M bench/results/identify.json\n M bench/results/deblur.json")
    assert run.tree_changed_beside_results("M src/napari_psfspace/__init__.py")
    assert run.tree_changed_beside_results(
        " M bench/results/identify.json\n M src/napari_psfspace/core/restore/identify.py\n")
    assert run.tree_changed_beside_results("R  bench/results/a.json -> bench/bench_a.py\n")
    assert run.tree_changed_beside_results(" M bench/run.py\n")


def test_a_tree_with_changes_records_no_result(monkeypatch, tmp_path):
    """A run from a tree with changes is refused before the bench starts; ``--scratch``
    runs it and saves nothing."""
    import pytest

    run = _runner()
    monkeypatch.setattr(run, "tree_changed_beside_results", lambda status=None: True)
    monkeypatch.setattr(run, "RESULTS", tmp_path)
    monkeypatch.setattr(run, "_git", lambda *args: "0" * 40)
    started = []
    monkeypatch.setattr(run.subprocess, "Popen", lambda *a, **k: started.append(a))
    with pytest.raises(SystemExit, match="committed tree"):
        run.run("accuracy", ["--quick"])
    assert not started and not list(tmp_path.iterdir())

    class Done:
        stdout = iter(["a | b\n", "1 | 2\n"])

        def wait(self):
            return 0

    monkeypatch.setattr(run.subprocess, "Popen", lambda *a, **k: Done())
    assert run.run("accuracy", ["--quick"], scratch=True) is None
    assert not list(tmp_path.iterdir())
