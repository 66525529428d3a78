"""The repository's hygiene: no large file, wheel or archive tracked; every package the
source imports is declared in ``pyproject.toml`` (a dependency, or the extra that the
importing part needs)."""

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: An import name -> its distribution, where they differ.
DISTRIBUTION = {"PIL": "pillow", "skimage": "scikit-image", "cupyx": "cupy-cuda12x",
                "cupy": "cupy-cuda12x"}
ARCHIVES = (".whl", ".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz", ".7z", ".egg")


def _tracked() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True,
                             check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: nothing tracked to check")
    return [ROOT / p for p in out.decode().split("\0") if p]


def test_no_large_file_wheel_or_archive_is_tracked():
    files = _tracked()
    assert len(files) > 100
    big = {str(p.relative_to(ROOT)): p.stat().st_size for p in files
           if p.exists() and p.stat().st_size > 1_000_000}
    assert not big, big
    archives = [str(p.relative_to(ROOT)) for p in files if p.name.endswith(ARCHIVES)]
    assert not archives, archives


def _declared() -> set[str]:
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    specs = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        specs += extra
    return {re.split(r"[\[<>=!~ ;]", s, maxsplit=1)[0].lower() for s in specs}


def _imported() -> dict[str, str]:
    """Top-level third-party modules imported under src (anywhere in a module), and one
    file that imports each."""
    out = {}
    for p in sorted((ROOT / "src").rglob("*.py")):
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "napari_psfspace":
                    out.setdefault(top, str(p.relative_to(ROOT)))
    return out


def test_every_imported_package_is_declared():
    declared = _declared()
    imported = _imported()
    assert {"numpy", "scipy", "tifffile"} <= set(imported)
    missing = {name: where for name, where in imported.items()
               if DISTRIBUTION.get(name, name).lower() not in declared}
    assert not missing, missing


def _constant_asserts(source: str) -> list[int]:
    """Lines of ``assert NAME == number`` (or ``number == NAME``) with NAME in capitals:
    a test of a constant's value, which checks nothing the code does."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if not (isinstance(node, ast.Assert) and isinstance(node.test, ast.Compare)):
            continue
        sides = [node.test.left, *node.test.comparators]
        names = [s for s in sides if isinstance(s, (ast.Name, ast.Attribute))]
        numbers = [s for s in sides if isinstance(s, ast.Constant)
                   and isinstance(s.value, (int, float)) and not isinstance(s.value, bool)]
        if names and numbers and all(
                re.fullmatch(r"[A-Z][A-Z0-9_]{2,}",
                             n.id if isinstance(n, ast.Name) else n.attr) for n in names):
            out.append(node.lineno)
    return out


def test_no_test_asserts_a_constant():
    found = {str(p.relative_to(ROOT)): lines for p in sorted((ROOT / "tests").rglob("*.py"))
             if (lines := _constant_asserts(p.read_text(encoding="utf-8")))}
    assert not found, found
    # the finder finds one
    assert _constant_asserts("assert PRIOR_WEIGHT == 0.5\nassert w == 0.5\n") == [1]


def test_every_listed_slow_test_exists():
    """``tests/slow_tests.txt`` (the tests ``make check`` leaves out) names tests that
    exist: a renamed test would silently come back into the fast set."""
    # read here, not imported: tests/widgets has a conftest of the same module name
    lines = (ROOT / "tests" / "slow_tests.txt").read_text(encoding="utf-8").splitlines()
    slow = {line.split()[-1] for line in lines if line.strip() and not line.startswith("#")}
    assert len(slow) > 20
    missing = []
    for node in slow:
        path, _, name = node.partition("::")
        func = name.split("[")[0].split("::")[-1]
        file = ROOT / path
        if not file.exists() or f"def {func}(" not in file.read_text(encoding="utf-8"):
            missing.append(node)
    assert not missing, missing


def test_source_comments_hold_no_diary():
    """Comments say what the code does, in the present tense: no issue numbers, no
    session words and no pointers into the benches' history (a reader has the code, not
    the project's diary). Another project's issue (``dask issue 11349``) is a fact about
    that code and stays."""
    diary = re.compile(r"RESULTS\.md@|(?<!dask )\bissue \d+|\b(first|second|third|fourth|"
                       r"fifth|sixth) session\b", re.IGNORECASE)
    found = [f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
             for path in sorted((ROOT / "src").rglob("*.py"))
             for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if diary.search(line)]
    assert not found, "\n".join(found)
