"""The front door: the whole method from ``import napari_psfspace``, and every name and
command the README and the docs use works as written.

* every name of ``__all__`` exists, the method's steps among them;
* ``import napari_psfspace`` pulls in no dask, napari or Qt (a fresh interpreter);
* every ``ps.NAME`` and every ``from napari_psfspace... import ...`` in ``README.md`` and
  ``docs/*.md`` resolves;
* every ``psfspace`` line of their shell blocks parses with the command line's own
  parser, and the quick blocks (no diagnosis, family or deblurring) run as written in
  an empty folder;
* every function with a generator twin (``NAME`` / ``iter_NAME``) takes the twin's
  parameters, with the same defaults, and ``progress``.
"""

import inspect
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

import napari_psfspace as ps
from napari_psfspace.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
METHOD = ["estimate_operator", "iter_estimate", "diagnose", "iter_diagnose",
          "estimate_family", "iter_estimate_family", "OperatorFamily", "load_family",
          "identify_operator", "deblur", "iter_deblur", "Deblurred", "load_operator",
          "ProductConvolution", "suggest_psf_radius", "Progress", "run_with_progress",
          "estimate_operator_3d", "ProductConvolution3D", "load_operator_3d"]


def test_the_whole_method_is_public():
    missing = [n for n in ps.__all__ if not hasattr(ps, n)]
    assert not missing
    assert not [n for n in METHOD if n not in ps.__all__]


def _loaded_after(statement: str) -> set[str]:
    """The modules a fresh interpreter holds after ``statement``."""
    code = f"import sys\n{statement}\nprint(' '.join(sorted(sys.modules)))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout.split()
    return set(out)


def test_import_pulls_in_no_gui_and_no_dask():
    # every public name resolved (the package imports each on first use)
    loaded = _loaded_after("import napari_psfspace as ps\n"
                           "[getattr(ps, n) for n in ps.__all__]")
    heavy = {"dask", "distributed", "napari", "qtpy", "PyQt5", "PyQt6", "PySide2", "PySide6",
             "magicgui", "vispy"}
    assert not {m.split(".")[0] for m in loaded} & heavy


def test_the_napari_readers_import_nothing_until_a_file_is_read():
    """napari imports a plugin's reader and writer modules to ask them about each file: that
    import loads neither the array libraries nor the method (they come with the file)."""
    loaded = _loaded_after("import napari_psfspace._reader, napari_psfspace._writer")
    heavy = {"numpy", "scipy", "tifffile", "zarr", "skimage", "dask", "napari"}
    assert not {m.split(".")[0] for m in loaded} & heavy
    assert not [m for m in loaded if m.startswith("napari_psfspace.core.")]


def _blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", text, flags=re.S)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_name_the_pages_use_exists(page):
    text = page.read_text(encoding="utf-8")
    names = set(re.findall(r"(?<![\w/.])ps\.([A-Za-z_]\w*)", text))
    assert not sorted(n for n in names if not hasattr(ps, n)), page.name
    for module, items in re.findall(r"from (napari_psfspace[\w.]*) import ([\w, ]+)", text):
        mod = __import__(module, fromlist=["_"])
        for item in (i.strip() for i in items.split(",")):
            assert hasattr(mod, item), f"{page.name}: from {module} import {item}"


def _commands(block: str) -> list[list[str]]:
    out = []
    for line in block.splitlines():
        line = line.split("#", 1)[0].strip()
        if line.startswith("psfspace "):
            out.append(shlex.split(line)[1:])
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_command_the_pages_show_parses(page):
    parser = build_parser()
    for block in _blocks(page.read_text(encoding="utf-8"), "bash"):
        for argv in _commands(block):
            try:
                parser.parse_args(argv)
            except SystemExit:
                pytest.fail(f"{page.name}: `psfspace {' '.join(argv)}` does not parse")


#: Commands quick enough to run from the README in the suite.
QUICK = {"simulate", "estimate", "psf", "apply"}


def test_the_readme_quick_blocks_run_as_written(tmp_path):
    """Each README shell block of quick commands, in an empty folder, with the
    ``psfspace`` this interpreter installed."""
    blocks = [b for b in _blocks((ROOT / "README.md").read_text(encoding="utf-8"), "bash")
              if _commands(b) and all(c[0] in QUICK and "--focus-series" not in c
                                      for c in _commands(b))]
    assert blocks, "the README shows no quick command block"
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}"
                                 f"{os.environ.get('PATH', '')}"}
    for block in blocks:
        done = subprocess.run(["bash", "-e", "-c", block], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "model.npz").exists() and (tmp_path / "blurred.tif").exists()


#: (function, its generator twin, the twin's parameters the function does not take:
#: the generator's extra hooks for the panel and the diagnosis).
TWINS = [
    ("estimate_operator", "iter_estimate", set()),
    ("diagnose", "iter_diagnose", set()),
    ("estimate_family", "iter_estimate_family", set()),
    ("deblur", "iter_deblur", set()),
    ("estimate_operator_3d", "iter_estimate_operator_3d", set()),
    ("core.restore.norm.operator_norm2", "core.restore.norm.iter_operator_norm2",
     set()),
]


def _resolve(name: str):
    obj = ps
    for part in name.split("."):
        obj = getattr(obj, part) if hasattr(obj, part) else __import__(
            f"{obj.__name__}.{part}", fromlist=["_"])
    return obj


@pytest.mark.parametrize("name, twin, extra", TWINS, ids=[t[0].rsplit(".", 1)[-1] for t in TWINS])
def test_every_function_takes_its_generators_parameters(name, twin, extra):
    f = inspect.signature(_resolve(name)).parameters
    g = inspect.signature(_resolve(twin)).parameters
    assert "progress" in f and f["progress"].default is None
    assert not [p for p in f.values() if p.kind is p.VAR_KEYWORD], f"{name} takes **kwargs"
    public = {k: p for k, p in g.items() if not k.startswith("_") and k not in extra}
    own = {k: p for k, p in f.items() if k != "progress"}
    assert list(own) == list(public), (name, list(own), list(public))
    for k, p in own.items():
        assert p.default == public[k].default, (name, k)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_link_is_to_what_a_clone_contains(page):
    """Relative links and images resolve inside the repository; nothing points to
    ``../shared`` (beside the repository in CI, not in a user's clone)."""
    text = page.read_text(encoding="utf-8")
    for target in re.findall(r"\]\(([^)#\s]+)[^)]*\)", text):
        if re.match(r"[a-z]+:", target):
            continue  # a web address
        path = (page.parent / target).resolve()
        assert path.is_relative_to(ROOT) and path.exists(), f"{page.name}: {target}"
    if page.name == "README.md":
        assert "../shared" not in text and not re.search(r"\bissue \d+", text)


def test_the_readme_is_a_front_page():
    """About 150 lines: what it is, a figure, set-up, three quick starts, citation and
    licence; the rest lives in docs/."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 170
    for heading in ("## Set-up", "## Quick start: napari", "## Quick start: Python",
                    "## Quick start: command line", "## Citation", "## Licence"):
        assert heading in text
    assert (ROOT / "CITATION.cff").exists() and "![" in text
