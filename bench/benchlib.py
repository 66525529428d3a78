"""Shared helpers of the benchmark scripts: their tables, the optics code of their
scenes, and the wait of the panel walks. The benches import the installed package
(``make install``); only :func:`use_checkout`, asked for by the benches that time two
checkouts, changes ``sys.path``."""

from __future__ import annotations

from pathlib import Path

#: This checkout's ``src`` (the benches that time two checkouts name it).
SRC = Path(__file__).resolve().parents[1] / "src"
#: This checkout (the default of ``--src``).
CHECKOUT = SRC.parent


def use_checkout(path) -> str:
    """Import ``napari_psfspace`` from the checkout at ``path`` (its ``src``), before the
    installed one; returns that ``src``. Stops if another copy was imported already."""
    import sys

    src = str(Path(path).resolve() / "src")
    sys.path.insert(0, src)
    import napari_psfspace

    if not napari_psfspace.__file__.startswith(src):
        raise SystemExit(f"imported {napari_psfspace.__file__}, not {src}")
    return src


def table(rows: list[dict], columns: list[tuple[str, str]]) -> str:
    """Plain-text table: ``columns`` is a list of (key, format) pairs."""
    heads = [k for k, _ in columns]
    cells = [[format(r[k], f) if r.get(k) is not None else "-" for k, f in columns]
             for r in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(heads)]
    line = " | ".join(h.rjust(w) for h, w in zip(heads, widths, strict=True))
    out = [line, "-" * len(line)]
    out += [" | ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join(out)


def optics_type(generator: str):
    """The optics class of a bench's scenes: the project's simulator ("ours") or pyotf
    ("pyotf": ``bench/independent.py``, the ``bench`` extra)."""
    if generator == "pyotf":
        from independent import PyotfOptics

        return PyotfOptics
    if generator == "psfmodels":
        from independent import PsfmodelsOptics

        return PsfmodelsOptics
    from napari_psfspace.core.simulation.optics import Optics

    return Optics


def add_generator_argument(parser) -> None:
    """``--generator {ours,pyotf}``: whose optics code computes the PSFs."""
    parser.add_argument("--generator", choices=("ours", "pyotf", "psfmodels"), default="ours",
                        help="the optics code of the PSFs: the project's simulator, or "
                             "pyotf (bench/independent.py; pip install -e '.[bench]')")


def wait_for(task, timeout: float = 600.0) -> None:
    """Process Qt events until a panel step's job is done (``task.running`` false), or
    ``timeout`` seconds; then a few more for its last draw."""
    import time

    from qtpy.QtWidgets import QApplication

    app = QApplication.instance()
    t0 = time.perf_counter()
    while task.running and time.perf_counter() - t0 < timeout:
        app.processEvents()
        time.sleep(0.01)
    for _ in range(10):
        app.processEvents()
        time.sleep(0.02)
