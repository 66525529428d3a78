"""The headless core must never import napari, Qt or magicgui.

The core is imported in a fresh interpreter in which those packages are blocked
(``sys.modules[name] = None`` makes any import of them fail), then every core module
is imported explicitly, so a GUI import anywhere in the core fails this test.
"""

import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

BLOCKED = ["napari", "qtpy", "PyQt5", "PyQt6", "PySide2", "PySide6", "magicgui", "superqt",
           "vispy"]
CORE = Path(__file__).resolve().parents[1] / "src" / "napari_psfspace" / "core"


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=120)


def test_core_imports_without_gui_packages():
    modules = sorted(p.stem for p in CORE.glob("*.py") if p.stem != "__init__")
    assert len(modules) >= 10, modules
    code = f"""
        import sys, importlib
        for name in {BLOCKED!r}:
            sys.modules[name] = None
        import napari_psfspace.core
        for mod in {modules!r}:
            importlib.import_module("napari_psfspace.core." + mod)
        import napari_psfspace, napari_psfspace.cli, napari_psfspace.io, napari_psfspace.demo
        leaked = [m for m in sys.modules if m.split(".")[0] in {BLOCKED!r}
                  and sys.modules[m] is not None]
        assert not leaked, leaked
        print("ok", len({modules!r}))
    """
    res = _run(code)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("ok")


def test_blocking_really_blocks():
    """Guard against a vacuous test: a blocked package must fail to import."""
    res = _run("""
        import sys
        sys.modules["napari"] = None
        import napari
    """)
    assert res.returncode != 0
    assert "ModuleNotFoundError" in res.stderr or "ImportError" in res.stderr


@pytest.mark.parametrize("path", sorted(CORE.glob("*.py")), ids=lambda p: p.name)
def test_core_sources_do_not_mention_gui_imports(path):
    pattern = re.compile(r"^\s*(from|import)\s+(" + "|".join(BLOCKED) + r")\b", re.MULTILINE)
    hits = pattern.findall(path.read_text())
    assert not hits, (path, hits)
