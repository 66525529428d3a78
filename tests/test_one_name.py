"""One name per module: every module has one import path, and no module outside the
tests imports another module's private (``_name``) name.

An import is resolved to the module it names (relative imports against the importing
file's package); a name imported from a module of this package that starts with one
underscore is private to that module. Checked over ``src``, ``bench`` and ``docs``.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
CHECKED = ("src", "bench", "docs")


def _package(path: Path, src: Path) -> list[str]:
    return list(path.relative_to(src).parts[:-1])  # the file's folder, __init__ or not


def private_imports(path: Path, src: Path = SRC) -> list[tuple[int, str, str]]:
    """(line, module, name) of every private name ``path`` imports from this package
    (``src``: the folder that holds the package)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            if not path.is_relative_to(src):
                continue  # a bench's own helpers (bench/benchlib.py)
            pkg = _package(path, src)
            base = pkg[: len(pkg) - (node.level - 1)]
            module = ".".join(base + ([node.module] if node.module else []))
        else:
            module = node.module or ""
        if not module.startswith("napari_psfspace"):
            continue
        out += [(node.lineno, module, a.name) for a in node.names
                if a.name.startswith("_") and not a.name.startswith("__")]
    return out


FILES = sorted(p for top in CHECKED for p in (ROOT / top).rglob("*.py"))


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_private_name_crosses_a_module(path):
    bad = private_imports(path)
    assert not bad, (f"{path.relative_to(ROOT)} imports private names of other modules "
                     f"(make them public where they are defined): {bad}")


def test_the_private_check_sees_a_violation(tmp_path):
    """Guard against a vacuous check: relative (inside a function too) and absolute."""
    probe = tmp_path / "napari_psfspace" / "core" / "beads" / "probe.py"
    probe.parent.mkdir(parents=True)
    probe.write_text("def f():\n    from ..model.pca import _orient, PsfBasis\n"
                     "from napari_psfspace.core.beads.scale import _x\n")
    found = sorted((m, n) for _, m, n in private_imports(probe, tmp_path))
    assert found == [("napari_psfspace.core.beads.scale", "_x"),
                     ("napari_psfspace.core.model.pca", "_orient")]


def test_no_module_has_a_second_import_path():
    """No meta-path finder or alias table gives a module a second name."""
    hits = [f"{p.relative_to(ROOT)}:{i}" for p in (SRC / "napari_psfspace").rglob("*.py")
            for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
            if "meta_path" in line or "MOVED" in line]
    assert not hits, hits
    assert len(FILES) > 100
