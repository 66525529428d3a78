"""The QC report's files: one self-contained HTML page (figures inline as PNG data, no
script, no network), a CSV a bead, and the JSON record (:mod:`.qc`).

:func:`write_qc_report` writes ``qc.html``, ``qc_beads.csv`` and ``qc.json`` into a
folder, each atomically (a reader never sees a half-written file).
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import os
from pathlib import Path

import numpy as np

from ..core.common.atomic import write_set
from ..figure import labelled_figure
from .qc import average_psf

#: The field maps of the page: measure, title, colour map.
MAPS = (("fwhm_col", "lateral FWHM along x (columns)", "viridis"),
        ("fwhm_row", "lateral FWHM along y (rows)", "viridis"),
        ("fwhm_axial", "axial FWHM", "viridis"),
        ("ellipticity", "ellipticity (1 - minor / major)", "magma"),
        ("focal_plane", "focal surface (above lowest)", "viridis"),
        ("astigmatic_split", "astigmatic split (x - y)", "diverging"))
#: Pixels of a figure's image (the longer side).
FIGURE_SIZE = 240

STYLE = ("body{font-family:sans-serif;max-width:1100px;margin:auto;color:#141414}"
         "table{border-collapse:collapse;margin:6px 0}td,th{border:1px solid #bbb;"
         "padding:2px 6px;text-align:right}th{background:#eee}.pass{color:#070}"
         ".fail{color:#b00;font-weight:bold}.figs img{margin:4px}"
         "@media print{.figs img{width:45%}}")


def _png(rgb: np.ndarray) -> str:
    from ..io import png_bytes

    data = png_bytes(np.asarray(rgb, np.uint8))
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def _img(values, alt: str, **kwargs) -> str:
    return (f'<img alt="{html.escape(alt)}" src="'
            f'{_png(labelled_figure(values, size=FIGURE_SIZE, **kwargs))}">')


def _table(header, rows) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _v(x, fmt=".4g") -> str:
    return "-" if x is None else format(x, fmt) if isinstance(x, float) else str(x)


def _map_figures(record: dict, voxel_size) -> str:
    if record["model"]["field_model"] == "shift-invariant":
        return ("<p><b>One PSF: no map of the field.</b> "
                f"{html.escape((record['model'].get('field_model_reason') or '').rstrip('.'))}"
                ". The beads' own values are in qc_beads.csv.</p>")
    maps = record["maps"]
    h, w = record["stack_shape"][1:]
    node_um = (h / len(maps["rows_px"]) * voxel_size[1]) if voxel_size else None
    out = []
    for name, title, cmap in MAPS:
        arr = np.array([[np.nan if v is None else v for v in row] for row in maps[name]],
                       float)
        unit = record["field"][name]["unit"]
        if voxel_size and unit == "nm":
            step = voxel_size[0] if name in ("fwhm_axial", "focal_plane",
                                             "astigmatic_split") else voxel_size[1]
            arr = arr * step * 1000
        if name == "focal_plane":
            arr = arr - np.nanmin(arr)
        if not np.isfinite(arr).any():
            out.append(f"<p>{html.escape(title)}: not measurable over the field</p>")
            continue
        lim = None
        if cmap == "diverging":
            m = float(np.nanmax(np.abs(arr))) or 1.0
            lim = (-m, m)
        out.append(_img(arr, title, title=title, unit=unit or "ratio", cmap=cmap,
                        limits=lim, pixel_size=node_um))
    return '<div class="figs">' + "".join(out) + "</div>"


def _crop(mean: np.ndarray, level: float = 0.02) -> tuple[slice, slice, slice]:
    """The box of the mean PSF above ``level`` of its peak, with a margin of a quarter
    of its size (at least 2 voxels) on each side."""
    idx = np.argwhere(mean >= level * float(mean.max()))
    lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
    pad = np.maximum((hi - lo) // 4, 2)
    lo, hi = np.maximum(lo - pad, 0), np.minimum(hi + pad, mean.shape)
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))


def _average_figures(estimation, voxel_size) -> str:
    from scipy import ndimage as ndi

    mean, sd = average_psf(estimation)
    peak = float(mean.max()) or 1.0
    if peak <= 0:
        return "<p>No average PSF: the beads' mean has no light.</p>"
    z = int(np.argmax(mean.max(axis=(1, 2))))
    cy, cx = np.unravel_index(int(np.argmax(mean[z])), mean.shape[1:])
    bz, by, bx = _crop(mean)
    px = voxel_size[1] if voxel_size else None
    # the x-z section in its true aspect: planes stretched by the z step over the pixel
    aspect = voxel_size[0] / voxel_size[2] if voxel_size else 1.0
    parts = []
    for arr, what in ((mean, "mean"), (sd, "SD")):
        lim = (0, 1) if what == "mean" else None
        xy = arr[z, by, bx] / peak
        xz = ndi.zoom(arr[bz, cy, bx] / peak, (aspect, 1.0), order=1)
        parts.append(_img(xy, f"{what} XY", title=f"{what} PSF, x-y at focus",
                          unit="of peak", cmap="magma", limits=lim, pixel_size=px))
        parts.append(_img(xz, f"{what} XZ", title=f"{what} x-z",
                          unit="of peak", cmap="magma", limits=lim, pixel_size=px,
                          note="z down, true aspect"))
    n = len(estimation.patches.psf[estimation.basis.inliers])
    return (f"<p>The mean and the standard deviation of the {n} beads' registered, "
            "normalised patches (each bead moved in z onto the focal surface), scaled to "
            "the mean's peak; cut to where the mean exceeds 2 % of it.</p>"
            + '<div class="figs">' + "".join(parts) + "</div>")


def qc_html(record: dict, estimation, voxel_size=None) -> str:
    """The page (module notes) of a record from :func:`~.qc.qc_record`."""
    r = record
    s = r["sampling"]
    e = html.escape
    title = f"PSF QC report: {e(r['source'] or 'bead stack')}"
    lines = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{title}</title>"
             f"<style>{STYLE}</style></head><body><h1>{title}</h1>",
             f"<p>{e(r['software'])}; stack {' x '.join(map(str, r['stack_shape']))} (z, y, "
             "x). Sampling: " + (f"{s['pixel_size_nm']} nm pixels, {s['z_step_nm']} nm "
                                 f"planes ({e(s['from'])})" if s["pixel_size_nm"] else
                                 "not known: lengths in pixels and planes") + ".</p>"]
    verdict = {True: "<span class='pass'>PASS</span>", False: "<span class='fail'>FAIL"
               "</span>", None: "not judged"}[r["passed"]]
    o = r["optics"]
    if o["na"] and o["wavelength_nm"]:
        lines.append(f"<p>Optics: NA {o['na']:g}, emission {o['wavelength_nm']:g} nm, "
                     f"immersion index {o['immersion_index']:g} "
                     f"({e(o['immersion_index_from'])}).</p>")
    if r["theory"] is None:
        verdict += " (no theory to compare with: give --na and --wavelength-nm)"
    lines.append(f"<h2>Verdict: {verdict}</h2>")
    rows = [[e(c["name"]), _v(c["value"]), _v(c["limit"]), e(c["why"]),
             {True: "<span class='pass'>pass</span>", False: "<span class='fail'>fail"
              "</span>", None: "-"}[c["pass"]]] for c in r["checks"]]
    lines.append(_table(["check", "value", "limit", "what", ""], rows))
    if r["warnings"]:
        lines.append("<h2>Warnings</h2><ul>" + "".join(f"<li>{e(w)}</li>"
                                                    for w in r["warnings"]) + "</ul>")
    th = _centre_section(r, lines)
    _field_section(voxel_size, r, lines, th)
    lines.append("<h2>Average PSF ± SD over the field</h2>")
    lines.append(_average_figures(estimation, voxel_size))
    _model_and_beads(r, lines)
    lines.append("</body></html>")
    return "\n".join(lines)


def _centre_section(r, lines):
    """The PSF at the field's centre: the beads' and the model's widths against theory."""
    e = html.escape
    lines.append("<h2>The PSF at the field's centre</h2>")
    th = r["theory"] or {}
    crow = []
    for name, key in (("lateral FWHM", "fwhm_lateral"), ("axial FWHM", "fwhm_axial")):
        short = "lateral" if key == "fwhm_lateral" else "axial"
        crow.append([name, _v(r["centre"][key]["value"]), _v(r["centre"][key]["model"]),
                     e(r["centre"][key]["unit"]),
                     _v((th.get("abbe") or {}).get(f"{short}_nm")),
                     _v((th.get("pupil_psf") or {}).get(f"{short}_nm"))])
    for key in ("fwhm_row", "fwhm_col", "fwhm_major", "fwhm_minor", "ellipticity",
                "astigmatic_split"):
        crow.append([key.replace("_", " "), _v(r["centre"][key]["value"]),
                     _v(r["centre"][key]["model"]), e(r["centre"][key]["unit"]), "-", "-"])
    lines.append(_table(["measure", "beads", "model", "unit", "Abbe (nm)",
                         "pupil PSF (nm)"], crow))
    lines.append("<p>Widths: a 2-D Gaussian with an offset in focus and a 1-D Gaussian "
                 "along the axis (the QUAREP-LiMi working group 5 practice, as "
                 "napari-psf-analysis fits them). <i>beads</i>: each bead fitted on its own "
                 "pixels, taken to the centre by a plane over the field (the figures "
                 "judged); <i>model</i>: the model's PSF at the centre (re-sampled to the "
                 "beads' sub-pixel centres, it reads wider where the PSF spans few "
                 "pixels). Theory, for a widefield microscope (a "
                 "confocal's is narrower): Abbe's widths and an aberration-free scalar pupil "
                 "PSF at this sampling, measured the same way."
                 "</p>")
    return th


def _field_section(voxel_size, r, lines, th):
    """The measures over the field against theory, their maps and the focal surface."""
    e = html.escape
    lines.append("<h2>Over the field</h2>")
    ref = th.get("pupil_psf") or th.get("abbe") or {}
    ideal = {"fwhm_lateral": ref.get("lateral_nm"), "fwhm_row": ref.get("lateral_nm"),
             "fwhm_col": ref.get("lateral_nm"), "fwhm_major": ref.get("lateral_nm"),
             "fwhm_minor": ref.get("lateral_nm"), "fwhm_axial": ref.get("axial_nm"),
             "ellipticity": 0.0, "astigmatic_split": 0.0}
    frows = []
    for k, v in r["field"].items():
        if k == "astigmatic_split_limit":
            continue
        want = ideal.get(k) if v["unit"] in ("nm", "") or k in ("ellipticity",
                                                                "astigmatic_split") else None
        if k == "focal_plane":
            want = "flat"
        frows.append([k.replace("_", " "), _v(v["min"]), _v(v["median"]), _v(v["max"]),
                      e(v["unit"]), _v(want) if want != "flat" else "flat"])
    lines.append(_table(["measure", "min", "median", "max", "unit", "theory"], frows))
    lines.append(_map_figures(r, voxel_size))
    fs = r["focal_surface"] or {}
    if fs:
        unit = "µm" if "tilt_um" in fs else "planes"
        lines.append(f"<p>Focal surface from {fs.get('n_beads')} beads' own foci: tilt "
                     f"{_v(fs.get('tilt_um', fs.get('tilt_planes')))} {unit} across the "
                     f"diagonal, curvature {_v(fs.get('curvature_um', fs.get('curvature_planes')))}"
                     f" {unit} centre to corner, beads scattered "
                     f"{_v(fs.get('sd_um', fs.get('sd_planes')))} {unit} about it; "
                     f"{fs.get('n_off', 0)} bead(s) left out off it.</p>")


def _model_and_beads(r, lines):
    """The model's own check, the diagnosis of the best-focus slice and the beads."""
    e = html.escape
    lines.append("<h2>The model's own check</h2>")
    m = r["model"]
    lines.append(f"<p>{m['n_psf']} 3D PSF(s), {e(m['field_model'])}; {e(m['verdict'])}.</p>")
    d = r.get("diagnosis")
    lines.append("<h2>Diagnosis of the best-focus slice</h2>")
    if d is None:
        lines.append("<p>Not run: <code>psfspace qc --diagnose</code> traces the held-out "
                     "residual of the best-focus slice's 2-D model to the effects it lacks "
                     "(a minute or more on a large slice).</p>")
    else:
        lines.append(f"<p>Slice {d['slice']}: {e(d['headline'])} Effects added: "
                     f"{e(', '.join(d['added']) or 'none')} (tried: "
                     f"{e(', '.join(d['tested']) or 'none')}).</p>")
        if d["unanswered"]:
            lines.append("<ul>" + "".join(f"<li>{e(u)}</li>" for u in d["unanswered"])
                         + "</ul>")
    b = r["beads"]
    lines.append(f"<h2>Beads: {b['used']} used of {b['detected']} detected</h2>")
    counts = ", ".join(f"{v} {e(k)}" for k, v in b["counts"].items() if v)
    lines.append(f"<p>{counts}. Each bead's direct fits: qc_beads.csv.</p>")
    if b["refused"]:
        lines.append(_table(["row (px)", "column (px)", "refused because"],
                            [[_v(x["row"], ".1f"), _v(x["col"], ".1f"), e(x["reason"])]
                             for x in b["refused"]]))


def _writer(data: bytes):
    """A writer of ``data`` to an open binary file."""
    return lambda fh: fh.write(data)


def write_qc_report(record: dict, estimation, out_dir: str | os.PathLike,
                    voxel_size=None) -> dict[str, Path]:
    """Write ``qc.html``, ``qc_beads.csv`` (``record["per_bead"]``) and ``qc.json`` into
    ``out_dir`` (made if missing); return their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    page = qc_html(record, estimation, voxel_size)
    rows = record["per_bead"]
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    paths = {"html": out / "qc.html", "csv": out / "qc_beads.csv", "json": out / "qc.json"}
    content = {"html": page, "csv": buf.getvalue(),
               "json": json.dumps(record, indent=1, allow_nan=False)}
    # one set, the page (its main file) last in: never one run's table beside another's
    write_set([(paths[k], _writer(content[k].encode("utf-8"))) for k in ("html", "csv", "json")])
    return paths


__all__ = ["FIGURE_SIZE", "MAPS", "qc_html", "write_qc_report"]
