"""The report of a diagnosis: ``report.json``, ``report.md`` and PNG figures.

:func:`write_report` turns a :class:`~napari_psfspace.core.diagnosis.loop.Diagnosis` into a
folder a microscopist can read (``report.md``), a program can parse (``report.json``,
documented in ``docs/report-format.md``) and figures (PNG, drawn with numpy alone):

* ``residual_map_before.png`` / ``residual_map_after.png``: each bead's held-out excess
  error (relative residual energy minus its noise floor) painted as a disk at its place
  in the field, on a coarse grid, viridis-like colours on one scale for both;
* ``mean_residual_before.png`` / ``mean_residual_after.png``: the mean normalised
  residual patch over the beads (grey ramp: black negative, mid-grey zero, white
  positive), one scale for both;
* ``residual_patches_before.png`` / ``residual_patches_after.png``: the normalised
  residual patches of the 16 worst beads (same ramp, clipped at +-5 noise sd).

The map builders (:func:`residual_map`, :func:`mean_residual_patch`,
:func:`worst_residual_patches`) are public: the *Diagnose* dock widget shows the same
maps as layers.

The parts: :mod:`.figures` (the maps as arrays), :mod:`.markdown` (``report.md``) and
:mod:`.record` (``report.json``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..core.common.atomic import write_set
from .figures import (
    FIGURES,
    PATCH_LIMIT,
    colorize,
    diverging_grey,
    excess_error,
    figure_arrays,
    map_cell_size,
    map_limit,
    mean_residual_patch,
    residual_map,
    worst_residual_patches,
)
from .markdown import (
    STEP_COLUMNS,
    floor_caveat,
    model_lines,
    noise_text,
    own_test_text,
    report_markdown,
    steps_table,
    summary_text,
)
from .record import REPORT_FORMAT, REPORT_VERSION, report_dict, to_jsonable


# ------------------------------------------------------------------ writing
def write_report(diagnosis, out_dir: str | os.PathLike, *, image_name: str = "image",
                 pixel_size: float | None = None, extra: dict | None = None) -> Path:
    """Write report.json, report.md and the PNG figures of a diagnosis into a folder.

    Parameters
    ----------
    diagnosis : Diagnosis
        From :func:`~napari_psfspace.core.diagnosis.loop.diagnose`.
    out_dir : str or path-like
        Folder, created if needed; files of the same names are replaced (atomically).
    image_name : str
        Name of the image in the report (e.g. its file name).
    pixel_size : float, optional
        Pixel size in micrometres, when known.
    extra : dict, optional
        More run information for report.json's ``run`` (JSON-serialisable).

    Returns
    -------
    Path
        The path of report.md.

    Raises
    ------
    ValueError
        ``out_dir`` exists and is not a folder.
    """
    from ..figure import figure_png

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{os.fspath(out)!r} is a file: give a folder for the report.")
    out.mkdir(parents=True, exist_ok=True)
    data = report_dict(diagnosis, image_name=image_name, pixel_size=pixel_size, extra=extra)
    fig = figure_arrays(diagnosis)
    px = pixel_size or diagnosis.operator.metadata.get("pixel_size_um")
    files = {}
    for when, which in (("before", "plain"), ("after", "final")):
        files[f"residual_map_{when}.png"] = figure_png(
            fig[f"map_{when}"], title=f"Held-out excess error, {which} model",
            unit="fraction of energy", limits=(0.0, fig["map_limit"]),
            pixel_size=px * fig["cell_size"] if px else None,
            note="each bead's error less its noise floor; grey: no bead")
        files[f"mean_residual_{when}.png"] = figure_png(
            fig[f"mean_{when}"], title=f"Mean residual, {which} model", unit="noise sd",
            limits=(-fig["mean_limit"], fig["mean_limit"]), cmap="grey", pixel_size=px,
            size=256)
        files[f"residual_patches_{when}.png"] = figure_png(
            fig[f"patches_{when}"], title=f"Residuals of the worst beads, {which} model",
            unit="noise sd", limits=(-PATCH_LIMIT, PATCH_LIMIT), cmap="grey")
    files["report.json"] = (json.dumps(data, indent=2, allow_nan=False) + "\n").encode()
    path = out / "report.md"
    md = report_markdown(diagnosis, data["run"], fig).encode("utf-8")
    # one set: report.md (the main file) only beside the figures and data of its run
    write_set([(path, lambda fh, b=md: fh.write(b))]
              + [(out / name, lambda fh, b=b: fh.write(b)) for name, b in files.items()])
    return path


__all__ = ["colorize", "diverging_grey", "excess_error", "figure_arrays", "FIGURES",
           "floor_caveat", "map_cell_size", "map_limit", "mean_residual_patch",
           "model_lines", "noise_text", "own_test_text", "PATCH_LIMIT", "report_dict",
           "REPORT_FORMAT", "report_markdown", "REPORT_VERSION", "residual_map",
           "STEP_COLUMNS", "steps_table", "summary_text", "to_jsonable",
           "worst_residual_patches", "write_report"]
