"""The headless core must never import napari, Qt or magicgui, and its stages import
one way only.

The core is imported in a fresh interpreter in which those packages are blocked
(``sys.modules[name] = None`` makes any import of them fail), then every core module
is imported explicitly, so a GUI import anywhere in the core fails this test.

The core has one folder per stage of the method (issue 10). Every import in every core
module, at the top or inside a function, is resolved to the stage it names; a stage may
import only itself, the stages before it and ``common`` (:data:`ALLOWED`).
"""

import ast
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


#: The stage folders, and what each may import besides itself (data flow one way:
#: beads -> model -> diagnosis / family -> restore -> volume (3D); the simulator beside
#: the flow).
ALLOWED = {
    "common": set(),
    "beads": {"common"},
    "model": {"common", "beads"},
    "diagnosis": {"common", "beads", "model"},
    "family": {"common", "beads", "model"},
    "subspace": {"common", "family"},  # family's name until 0.2.0: an alias, deprecated
    "restore": {"common", "beads", "model", "family", "diagnosis"},
    "simulation": {"common", "beads"},
    "volume": {"common", "beads", "model", "diagnosis", "restore"},
}


def _module_names() -> list[str]:
    names = []
    for p in sorted(CORE.rglob("*.py")):
        parts = list(p.relative_to(CORE).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if parts:
            names.append(".".join(parts))
    return names


def test_core_imports_without_gui_packages():
    modules = _module_names()
    assert len(modules) >= 40, modules
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


@pytest.mark.parametrize("path", sorted(CORE.rglob("*.py")),
                         ids=lambda p: str(p.relative_to(CORE)))
def test_core_sources_do_not_mention_gui_imports(path):
    pattern = re.compile(r"^\s*(from|import)\s+(" + "|".join(BLOCKED) + r")\b", re.MULTILINE)
    hits = pattern.findall(path.read_text())
    assert not hits, (path, hits)


def test_the_core_is_made_of_the_stage_folders():
    folders = {p.name for p in CORE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == set(ALLOWED), folders
    # nothing but the package's own __init__ lies loose beside the stages
    assert sorted(p.name for p in CORE.glob("*.py")) == ["__init__.py"]
    for stage in ALLOWED:  # each stage says what it takes and gives
        doc = ast.get_docstring(ast.parse((CORE / stage / "__init__.py").read_text()))
        assert doc and len(doc) > 100, stage


def _imported_stages(path: Path) -> list[tuple[int, str]]:
    """(line, stage) of every core stage a module imports, relative or absolute."""
    rel = path.relative_to(CORE).with_suffix("").parts
    package = list(rel[:-1]) if rel[-1] != "__init__" else list(rel[:-1])
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.ImportFrom):
            if node.level:
                up = node.level - 1
                if up > len(package):  # above the core: the package's root
                    continue
                base = package[:len(package) - up]
                targets.append(base + (node.module.split(".") if node.module else []))
                if not node.module:  # from . import a, b: a and b may be modules
                    targets += [base + [a.name] for a in node.names]
            elif node.module and node.module.startswith("napari_psfspace.core."):
                targets.append(node.module.split(".")[2:])
        elif isinstance(node, ast.Import):
            targets += [a.name.split(".")[2:] for a in node.names
                        if a.name.startswith("napari_psfspace.core.")]
        out += [(node.lineno, t[0]) for t in targets if t]
    return out


@pytest.mark.parametrize("path", sorted(CORE.glob("*/**/*.py")),
                         ids=lambda p: str(p.relative_to(CORE)))
def test_no_import_runs_back_up_the_stages(path):
    stage = path.relative_to(CORE).parts[0]
    allowed = ALLOWED[stage] | {stage}
    bad = [(line, s) for line, s in _imported_stages(path) if s not in allowed]
    assert not bad, f"{path.relative_to(CORE)} imports a later stage: {bad}"


def test_the_import_check_sees_a_violation():
    """Guard against a vacuous check: an import from a later stage is caught, relative
    (inside a function too) or absolute."""
    fake = CORE / "beads" / "_probe_not_a_module.py"
    assert not fake.exists()
    src = "def f():\n    from ..model.estimate import iter_estimate\n"
    src += "import napari_psfspace.core.diagnosis.loop\n"
    try:
        fake.write_text(src)
        assert sorted(s for _, s in _imported_stages(fake)) == ["diagnosis", "model"]
    finally:
        fake.unlink()


# --------------------------------------------------------------------------- no circles
SRC = CORE.parents[1]


def _import_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports, at the top or inside a function
    (``from pkg import name`` counts as importing ``pkg.name`` where that is a module,
    else ``pkg``)."""
    mods: dict[str, tuple[Path, list[str]]] = {}
    for p in SRC.rglob("*.py"):
        parts = list(p.relative_to(SRC).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
            package = parts
        else:
            package = parts[:-1]
        mods[".".join(parts)] = (p, package)

    def known(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, (p, package) in mods.items():
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                base = (".".join(package[:len(package) - node.level + 1]
                                 + ([node.module] if node.module else []))
                        if node.level else (node.module or ""))
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base
                         for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                target = known(name) if name.startswith("napari_psfspace") else None
                if target and target != m:
                    graph[m].add(target)
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle_under_src():
    graph = _import_graph()
    assert len(graph) > 100 and graph["napari_psfspace.core.beads.detect"]
    assert not _circles(graph), _circles(graph)


def test_the_circle_finder_finds_a_circle():
    """Guard against a vacuous test: a circle of three is found, a chain is not."""
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_no_module_over_600_lines():
    long = {str(p.relative_to(SRC)): n for p in SRC.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 600}
    assert not long, long


def test_the_core_never_imports_the_top_package():
    graph = _import_graph()
    top = [m for m, targets in graph.items()
           if m.startswith("napari_psfspace.core") and "napari_psfspace" in targets]
    assert not top, top
