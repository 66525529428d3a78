"""No bench figure lives in the source: a time, an error measured on some scene, a seed,
an anecdote about one data set. Those rot with the next change; the rule stays in the
code with a pointer to the bench that measures it, the figure goes to
``bench/RESULTS.md``.

Every comment and docstring under ``src/`` is read; a line is a figure when it matches
one of :data:`FIGURE` (a duration, "seed N", "measured ... N", a ratio "1.4x", a before
and after "A -> B" / "A against B", a named measured set or slice). Lines holding a
physical or statistical constant (:data:`ALLOWED`) pass.
"""

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "napari_psfspace"

FIGURE = {
    "a duration": r"\b\d+(\.\d+)?\s*(ms|s|sec|seconds|min|minutes|h|hours)\b(?![-/])",
    "a seed": r"\bseeds?\s+\d",
    "a measured figure": r"\bmeasured\b[^.;]*\d",
    "a ratio": r"(?<![\w.<>=])(?<![<>=] )\d+(\.\d+)?\s?x\b(?!\s*\d)",
    "a before and after": r"(?<![-\w.])\d+(\.\d+)?\s*(->|against|instead of)\s*[~-]?\d",
    "a measured set": r"\bSP8\b|\bslice \d+\b|\bseries045\b",
    "a bench's figure": r"\bbench\w*\.py\b[^.;]*\d\.\d",
    "a result on some scene": (r"\b(gave|took|dropped|improved by)\s+([a-z]+\s+){0,2}[~-]?\d"
                               r"|\bp = 0\.\d|\bon \d+ (beads|images|slices|scenes)\b"),
}
#: Constants of physics or statistics (not figures of a bench).
ALLOWED = ("Nyquist", "1.0605", "1.4826", "2.858", "sqrt(1/12)", "efficiency")


def texts(path: Path):
    """(line, text) of every comment and docstring line of a module."""
    src = path.read_text(encoding="utf-8")
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                for i, line in enumerate(doc.splitlines()):
                    yield node.body[0].lineno + i, line


def figures(path: Path) -> list[str]:
    out = []
    for line, text in texts(path):
        if any(a in text for a in ALLOWED):
            continue
        for what, pattern in FIGURE.items():
            if re.search(pattern, text, flags=re.IGNORECASE):
                out.append(f"{line} ({what}): {text.strip()}")
                break
    return out


@pytest.mark.parametrize("path", sorted(SRC.rglob("*.py")), ids=lambda p: p.name)
def test_no_bench_figure_in_the_source(path):
    found = figures(path)
    assert not found, (f"{path.relative_to(SRC)}: bench figures in comments or docstrings "
                       "(keep the rule, point at the bench, put the figure in "
                       "bench/RESULTS.md):\n" + "\n".join(found))


def test_the_figure_check_sees_figures(tmp_path):
    """Guard against a vacuous check: each kind is caught, a constant passes."""
    probe = tmp_path / "probe.py"
    probe.write_text('"""Took 12.5 s on 2 cores.\n\nMeasured: 160 spots.\n"""\n'
                     "# seed 3 gave it\n# 1.47x one image's error\n# 0.92 against 0.88\n"
                     "# on SP8 slice 35\n# 418 -> 256 ms\n"
                     "# the MAD's efficiency is 37 %, 1.4826 sd\n# a 3 x 3 window, 1024 x 1024\n")
    found = figures(probe)
    assert len(found) == 7, found
