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
"""

from __future__ import annotations

import json
import math
import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .core.common.atomic import atomic_write
from .core.common.measures import field_fwhm, fwhm_line, in_units
from .core.common.mosaic import mosaic
from .core.diagnosis import metric
from .core.diagnosis.residuals import BeadResiduals

#: ``format`` and ``version`` of report.json (docs/report-format.md).
REPORT_FORMAT = "napari-psfspace/diagnosis-report"
REPORT_VERSION = 1
#: Figure files written by :func:`write_report`, with what each shows.
FIGURES = {
    "residual_map_before.png": "held-out excess error of each bead over the field, "
                               "plain model",
    "residual_map_after.png": "held-out excess error of each bead over the field, "
                              "final model",
    "mean_residual_before.png": "mean normalised residual patch over the beads, plain model",
    "mean_residual_after.png": "mean normalised residual patch over the beads, final model",
    "residual_patches_before.png": "normalised residual patches of the 16 worst beads, "
                                   "plain model",
    "residual_patches_after.png": "normalised residual patches of the 16 worst beads, "
                                  "final model",
}
#: Columns of :func:`steps_table`.
STEP_COLUMNS = ("effect", "stage", "evidence", "tests", "own test", "held-out error", "chi2/dof",
                "paired error drop", "p", "paired excess chi2 drop", "p (chi2)",
                "photometric drop", "decision")
#: Largest |normalised residual| (noise sd) shown in the patch mosaics.
PATCH_LIMIT = 5.0

# ------------------------------------------------------------------ maps (numpy only)
def excess_error(res: BeadResiduals) -> np.ndarray:
    """Each bead's relative residual energy minus what noise alone leaves, shape (K,)."""
    return np.asarray(res.rel_energy, float) - np.asarray(res.floor, float)


def map_cell_size(shape: tuple[int, int], cells: int = 64) -> float:
    """Pixels per cell of a :func:`residual_map` of an image of this shape."""
    return max(shape) / float(cells)


def residual_map(positions, values, shape: tuple[int, int], *, cells: int = 64,
                 radius: float | None = None) -> np.ndarray:
    """A coarse map of the field where each bead paints a disk of its value.

    Parameters
    ----------
    positions : array_like of shape (K, 2)
        Bead centres (row, column) in pixels of the image.
    values : array_like of shape (K,)
        One value per bead (non-finite ones are left out).
    shape : tuple of int
        ``(M, N)`` of the image.
    cells : int
        Cells along the longer side of the image (square cells of
        :func:`map_cell_size` pixels).
    radius : float, optional
        Disk radius in cells; default ``0.35`` of the mean spacing of the beads, between
        1 and 6 cells.

    Returns
    -------
    ndarray of shape (ceil(M / c), ceil(N / c)), float64
        NaN where no bead paints; where disks overlap the larger value shows.
    """
    pos = np.asarray(positions, float).reshape(-1, 2)
    val = np.asarray(values, float).reshape(-1)
    if len(pos) != len(val):
        raise ValueError(f"{len(pos)} positions but {len(val)} values.")
    cell = map_cell_size(shape, cells)
    gh, gw = math.ceil(shape[0] / cell), math.ceil(shape[1] / cell)
    out = np.full((gh, gw), np.nan)
    ok = np.isfinite(val) & np.all(np.isfinite(pos), axis=1)
    pos, val = pos[ok], val[ok]
    if not len(val):
        return out
    if radius is None:
        radius = float(np.clip(0.35 * np.sqrt(gh * gw / len(val)), 1.0, 6.0))
    yy, xx = np.mgrid[0:gh, 0:gw] + 0.5
    for k in np.argsort(val, kind="stable"):  # largest painted last: on top
        cy, cx = (pos[k] + 0.5) / cell
        out[(yy - cy) ** 2 + (xx - cx) ** 2 <= radius**2] = val[k]
    return out


def mean_residual_patch(res: BeadResiduals) -> np.ndarray:
    """Mean normalised residual patch over the beads (pixels in each bead's fit), (P, P).

    Pixels no bead fitted are 0.
    """
    if len(res) == 0:
        return np.zeros(res.data.shape[1:])
    nres = np.where(res.fit_mask, res.normalised_residual, 0.0)
    count = res.fit_mask.sum(axis=0)
    return nres.sum(axis=0) / np.maximum(count, 1)


def worst_residual_patches(res: BeadResiduals, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Normalised residual patches of the ``n`` beads of largest excess error.

    Returns
    -------
    patches : ndarray of shape (min(n, K), P, P)
        Worst first; 0 outside each bead's fit.
    index : ndarray of shape (min(n, K),)
        Their entries in ``res``.
    """
    order = np.argsort(-np.nan_to_num(excess_error(res), nan=-np.inf), kind="stable")[:n]
    return np.where(res.fit_mask[order], res.normalised_residual[order], 0.0), order


def map_limit(*maps: np.ndarray, percentile: float = 98.0) -> float:
    """A common upper colour limit for residual maps: a high percentile of their values."""
    vals = np.concatenate([np.ravel(m) for m in maps]) if maps else np.zeros(0)
    vals = vals[np.isfinite(vals)]
    hi = float(np.percentile(vals, percentile)) if len(vals) else 0.0
    return hi if hi > 0 else 1.0


def colorize(values: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """Viridis RGB image of a 2-D array (NaN: dark grey), uint8 (M, N, 3)
    (:func:`~napari_psfspace.figure.apply_colormap`)."""
    from .figure import apply_colormap

    return apply_colormap(values, vmin, vmax, "viridis")


def diverging_grey(values: np.ndarray, limit: float) -> np.ndarray:
    """Grey ramp: ``-limit`` black, 0 mid-grey, ``+limit`` white (clipped), uint8."""
    v = np.nan_to_num(np.asarray(values, float))
    t = np.clip(v / (limit if limit > 0 else 1.0), -1.0, 1.0)
    return np.round(127.5 + 127.5 * t).astype(np.uint8)


def figure_arrays(diagnosis, *, cells: int = 64, n_patches: int = 16) -> dict[str, Any]:
    """The figures of a diagnosis as arrays, before and after on common scales.

    Parameters
    ----------
    diagnosis : Diagnosis
    cells : int
        Cells along the longer side of the residual maps.
    n_patches : int
        Worst beads shown in the patch mosaics.

    Returns
    -------
    dict
        ``map_before``, ``map_after`` (float maps, NaN without a bead), ``map_limit``,
        ``cell_size`` (pixels per cell), ``mean_before``, ``mean_after`` (P, P),
        ``mean_limit``, ``patches_before``, ``patches_after`` (mosaics of normalised
        residuals).
    """
    shape = diagnosis.context.image.shape
    out: dict[str, Any] = {"cell_size": map_cell_size(shape, cells)}
    for when, cf in (("before", diagnosis.crossfit_before), ("after", diagnosis.crossfit_after)):
        res = cf.residuals
        out[f"map_{when}"] = residual_map(res.positions, excess_error(res), shape, cells=cells)
        out[f"mean_{when}"] = mean_residual_patch(res)
        tiles, _ = worst_residual_patches(res, n_patches)
        out[f"patches_{when}"] = (mosaic(tiles, gap=1, normalize="none") if len(tiles)
                                  else np.zeros((1, 1)))
    out["map_limit"] = map_limit(out["map_before"], out["map_after"])
    out["mean_limit"] = float(max(np.abs(out["mean_before"]).max(),
                                  np.abs(out["mean_after"]).max())) or 1.0
    return out


# ------------------------------------------------------------------ tables and text
def _num(x, fmt: str = ".4g") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return format(x, fmt)


def steps_table(diagnosis) -> list[list[str]]:
    """The steps as rows of text, one per step, in the order of :data:`STEP_COLUMNS`."""
    rows = []
    for s in diagnosis.steps:
        if s.effect is None:
            rows.append(["baseline", "", "", ", ".join(s.tests) or "-", "",
                         _num(s.error_before), _num(s.chi2_before, ".3g"), "", "", "", "", "",
                         "plain model"])
            continue
        cmp = (s.params or {}).get("_comparison") or {}
        chi2_drop = cmp.get("chi2_improvement")
        n = s.n_beads
        if "_error" in (s.params or {}):
            drop = f"not applied ({s.params['_error']})"
        elif "note" in cmp or not math.isfinite(s.improvement):
            drop = cmp.get("note", "not compared")
        else:
            drop = f"{_num(100 * s.improvement, '.1f')} % ({n} beads)"
        rows.append([s.effect, s.stage, _num(s.evidence, ".2f"), ", ".join(s.tests) or "-",
                     own_test_text(s.statistic),
                     f"{_num(s.error_before)} -> {_num(s.error_after)}",
                     f"{_num(s.chi2_before, '.3g')} -> {_num(s.chi2_after, '.3g')}",
                     drop,
                     _num(s.p_no_drop, ".3g"),
                     "" if chi2_drop is None else f"{_num(100 * chi2_drop, '.1f')} %",
                     _num(cmp["chi2_p_no_drop"], ".3g") if "chi2_p_no_drop" in cmp else "",
                     (f"{_num(100 * cmp['photometric_improvement'], '.1f')} % "
                      f"(p {_num(cmp['photometric_p_no_drop'], '.3g')})")
                     if "photometric_improvement" in cmp else "",
                     _decision(s)])
    return rows


def own_test_text(stat: dict | None) -> str:
    """A step's own test before -> after, with its threshold ("" without one)."""
    if not stat:
        return ""
    after = "not read" if stat.get("after") is None else _num(stat["after"], ".3g")
    return (f"{stat['test']} {_num(stat['before'], '.3g')} -> {after} "
            f"(threshold {_num(stat['threshold'], '.3g')})")


def _decision(s) -> str:
    if s.effect == "motion" and not s.accepted:
        return "found, kept in the model (remove_motion to divide it out)"
    if s.effect == "motion":
        return "divided out of the final operator"
    if s.accepted and (s.params or {}).get("_kept_by"):
        return "kept (its own test no longer significant, held-out error not worse)"
    return "kept" if s.accepted else "rejected"


def summary_text(diagnosis) -> str:
    """A few lines: the verdict, what was added, the held-out error before -> after and
    the floor."""
    d = diagnosis
    v = d.verdict
    if d.added:
        added = ", ".join(d.added)
    elif v.level != "not explained":
        added = "nothing (no effect was found)"
    else:
        added = "nothing (no candidate effect lowered the error)"
    hot = (f"{len(d.hot_pixels)} hot pixel(s) masked (narrower than the optics can form)\n"
           if len(d.hot_pixels) else "")
    kind = d.context.noise.kind
    assumed = ("" if kind in ("camera", "photon transfer") else
               f"\nnoise model assumed ({kind}: photon transfer was not possible): the floor "
               "and chi2/dof are only indicative")
    plain = "" if d.heldout is None else f"plain model: {d.heldout.line()}\n"
    return (f"{v.headline}\n{hot}{plain}added: {added}\n"
            f"held-out error {_num(d.error_before)} -> {_num(d.error_after)} on "
            f"{d.n_beads} beads (noise floor {_num(d.noise_floor)}); chi2/dof "
            f"{_num(d.chi2_before, '.3g')} -> {_num(d.chi2_after, '.3g')}{assumed}")


def floor_caveat(noise, ratio: float) -> str:
    """A sentence for a noise floor that rests on an assumed noise model (a fallback)."""
    if noise.kind in ("camera", "photon transfer"):
        return ""
    text = (f" The noise model is assumed ({noise.kind}; photon transfer was not possible, "
            "see below): the floor and the chi-square are only indicative")
    if ratio < 0.8:
        text += (", and here the error is below the floor: the assumed model overstates the "
                 "noise (e.g. a camera of less than 1 ADU per photon). Pass the camera's "
                 "gain, offset and read noise to judge against the true floor")
    elif noise.kind == "constant":
        text += ("; one variance for all pixels understates the shot noise of bright bead "
                 "cores, so the chi-square there is overstated")
    return text + "."


def model_lines(meta: dict, *, markdown: bool = True) -> list[str]:
    """What a reader must be told of a model: a field model chosen for a handful of beads
    (shift-invariant or affine, and why), a bead size divided out, motion blur found
    (and removed, when asked). Markdown paragraphs
    (each after an empty line), or plain lines."""
    def bold(text):
        return f"**{text}**" if markdown else text

    out = []
    sat = meta.get("saturation") or {}
    if sat.get("beads"):
        out.append(bold("Saturation") + f": {sat['beads']} of {sat.get('detections', '?')} "
                   f"detections have clipped pixels in their cores (level "
                   f"{sat.get('level', float('nan')):g}, {sat.get('pixels', 0)} pixels); "
                   f"{(meta.get('bead_counts') or {}).get('saturated', 0)} of them were left "
                   "out as saturated. Diagnose tries the saturation effect on them.")
    if meta.get("field_model") == "shift-invariant":
        out.append(bold("The model is shift-invariant") + " (one PSF for the whole field): "
                   + str(meta.get("field_model_reason", "")))
    elif meta.get("field_model") == "affine":
        out.append(bold("The field model is affine") + " (PSF weights vary as planes): "
                   + str(meta.get("field_model_reason", "")))
    elif meta.get("field_model_reason"):
        out.append(bold("The field model was chosen for few beads") + ": "
                   + str(meta["field_model_reason"]))
    used = meta.get("n_beads_used")
    left = (meta.get("left_out") or {}).get("beads", [])
    if used is not None and used <= 10:  # a few-bead model: each bead counts
        pos = meta.get("bead_positions") or []
        lines = [f"({p[0]:.0f}, {p[1]:.0f})" for p in pos]
        text = (bold(f"Beads used: {used}") + (" at " + ", ".join(lines) if lines else "")
                + " (row, column).")
        if left:
            text += " Left out: " + "; ".join(
                f"({b['position'][0]:.0f}, {b['position'][1]:.0f}) {b['status']}: {b['why']}"
                for b in left[:20]) + ("; ..." if len(left) > 20 else "") + "."
        out.append(text)
    fd = meta.get("field_dof") or {}
    if fd.get("note"):
        out.append(bold("A rich field") + ": " + str(fd["note"]) + ".")
    corr = meta.get("bead_correction")
    if corr:
        out.append(bold("Bead size corrected") + f": the beads' diameter, "
                   f"{_num(corr['diameter_px'], '.3g')} px, was divided out of the learnt "
                   "PSFs (in Fourier, where the signal stands above the noise: up to "
                   f"{_num(corr.get('band_px'), '.3g')} cycles/px, gain at most "
                   f"{_num(corr.get('max_gain_applied'), '.3g')}): the model's PSFs are "
                   "those of a point source."
                   + (" " + corr["warning"] if corr.get("warning") else ""))
    motion = meta.get("motion") or {}
    if motion.get("detected"):
        removed = motion.get("removed")
        out.append(bold("Motion blur") + ": " + str(motion.get("reason", "")) + "."
                   + (f" Removed from the model's PSFs (gain at most "
                      f"{_num(removed.get('max_gain_applied'), '.3g')}; what the smear "
                      "erased near its zero lines is not restored)." if removed else ""))
    elif motion.get("note"):
        out.append(bold("Motion blur") + ": " + str(motion["note"]) + ".")
    if not markdown:
        return out
    return [line for text in out for line in ("", text)]


def noise_text(noise) -> str:
    """The noise model in a sentence: the model, how it was obtained, what it implies."""
    if noise.kind == "constant":
        text = (f"One variance for every pixel, {_num(noise.intercept)} ADU², measured on the "
                "background. Photon transfer was not possible: ")
        return text + noise.note.split("photon transfer not possible (", 1)[-1]
    text = (f"Variance = {_num(noise.gain)} x mean {'+' if noise.intercept >= 0 else '-'} "
            f"{_num(abs(noise.intercept))} ADU² (gain {_num(noise.gain)} ADU/e-"
            + (f", offset {_num(noise.offset)} ADU" if noise.offset is not None else "")
            + (f", read noise {_num(noise.read_noise)} e-" if noise.read_noise is not None
               else "") + "). ")
    if noise.kind == "camera":
        return text + "Source: the camera's values, as given."
    if noise.kind == "photon transfer":
        chk = noise.checks or {}
        rel = chk.get("gain_relative_error")
        return (text + "Source: photon transfer on the image"
                + (f" (gain to within {_num(100 * rel, '.2g')} %, " if rel else " (")
                + f"{chk.get('n_levels', 0)} levels over {_num(noise.mean_range[0])}-"
                  f"{_num(noise.mean_range[1])} ADU, fit reduced chi-square "
                  f"{_num(chk.get('fit_chi2'), '.3g')}).")
    return text + f"Fallback ({noise.kind}): {noise.note}."


def _md_table(header, rows) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c).replace("|", "/") for c in r) + " |" for r in rows]
    return lines


def _tests_section(analysis, when: str) -> list[str]:
    sig = analysis.significant()
    if not sig:
        return [f"{when}: no test is significant: the residuals look like noise to every "
                "test.", ""]
    rows = [[t.name, _num(t.z, ".3g"), _num(t.threshold, ".3g"), _num(t.evidence, ".2f")]
            for t in sig]
    return [f"{when}: {len(sig)} significant test(s), strongest first:", "",
            *_md_table(("test", "z", "threshold", "z / threshold"), rows), ""]


def _effect_descriptions(diagnosis) -> dict[str, str]:
    from .core.diagnosis.corrections import CORRECTIONS
    from .core.diagnosis.effects import REGISTRY

    out = {}
    for s in diagnosis.steps:
        if s.effect and s.effect in REGISTRY:
            out[s.effect] = REGISTRY[s.effect].description
        elif s.effect in CORRECTIONS:
            out[s.effect] = CORRECTIONS[s.effect]
    return out


def report_markdown(diagnosis, run: dict, fig: dict) -> str:
    """The text of report.md (see :func:`write_report`)."""
    d = diagnosis
    descr = _effect_descriptions(d)
    px = run.get("pixel_size_um")
    lines = [f"# PSF model diagnosis: {run['image']}", "",
             f"napari-psfspace {run['version']}, {run['date']}. Image "
             f"{run['image_shape'][0]} x {run['image_shape'][1]} px"
             + (f" at {px:g} µm/px" if px else "")
             + f"; PSF radius {run['psf_radius_px']:.3g} px; "
             f"{len(d.crossfit_before.residuals)} beads judged by models that did not see "
             "them (cross-fitting).", "", "## What was found", ""]
    v = d.verdict
    lines += [f"**{v.headline}**", ""]
    if v.hints:
        lines += ["What to look at:", "", *[f"- {h}" for h in v.hints], ""]
    drop = (1 - d.error_after / d.error_before) if d.error_before else float("nan")
    if d.added:
        lines.append("The model lacked, and now includes:")
        lines.append("")
        lines += [f"- **{name}**: {descr.get(name, '')}" for name in d.added]
        lines += ["", f"Held-out error {_num(d.error_before)} -> {_num(d.error_after)} "
                      f"({_num(100 * drop, '.1f')} % lower) on the same {d.n_beads} beads; "
                      f"chi-square per degree of freedom {_num(d.chi2_before, '.3g')} -> "
                      f"{_num(d.chi2_after, '.3g')}."]
    else:
        tried = [s.effect for s in d.steps if s.effect and s.stage == "effect"]
        sig = [t.name for t in d.analysis_before.significant()]
        if tried:
            why = (f"{len(tried)} candidate(s) tried ({', '.join(tried)}), none lowered the "
                   "held-out error significantly")
        elif sig:
            why = (f"{len(sig)} residual test(s) significant ({', '.join(sig)}), none "
                   "answered by a candidate effect")
        else:
            why = "no residual test is significant"
        head = ("**No effect was added**" if v.level == "not explained"
                else "**No effect was found**")
        lines.append(f"{head}: {why}; the plain model is kept.")
        lines += ["", f"Held-out error {_num(d.error_after)} on {d.n_beads} beads; "
                      f"chi-square per degree of freedom {_num(d.chi2_after, '.3g')}."]
    lines += model_lines(d.operator.metadata)
    lines += ["", fwhm_line(field_fwhm(d.operator), px) + "."]
    motion = d.operator.metadata.get("motion") or {}
    if motion and not motion.get("detected") and not motion.get("note"):
        lines += ["", "**Motion blur**: " + str(motion.get("reason", "not tested")) + "."]
    af = d.analysis_before.tests.get("amplitude_field")
    if af is not None and "illumination" not in d.added and af.significant:
        lines += ["", f"**Vignetting**: the beads' brightness varies over the field "
                      f"(amplitude_field z {_num(af.z, '.3g')} > {_num(af.threshold, '.3g')}), "
                      "but a smooth throughput did not lower the held-out error: not "
                      "added (the variation may be the beads' own)."]
    elif af is not None and "illumination" not in d.added and "min_corner_loss" in af.detail:
        lines += ["", "**Vignetting**: none found; with these beads' brightness spread and "
                      "number, a fall-off from the centre to the corners of "
                      f"{_num(100 * af.detail['min_corner_loss'], '.0f')} % or more "
                      "would have been seen (a weaker one cannot be told from the beads' "
                      "own differences)."]
    if d.options.get("leave_one_bead_out"):
        lines += ["", f"With {d.options['folds']} usable beads, each bead was judged by a "
                      "model learnt from all the others (leave-one-bead-out)."]
    n_hot = len(d.hot_pixels)
    if n_hot:
        lines += ["", f"**Hot pixels**: {n_hot} pixel(s) narrower than the optics can form "
                      "(hot pixels, cosmic rays: a bright pixel, or two, on a dark "
                      "neighbourhood) were masked before anything was fitted; their "
                      "positions are in `report.json` (`hot_pixels`)."]
    ratio = v.ratio
    lines += ["", f"Noise alone would leave an error of {_num(d.noise_floor)} (the noise "
                  f"floor): the final model's error is {_num(ratio, '.3g')} times the floor"
                  + (" (it explains everything but the noise)." if v.level == "explained"
                     else " (what is left above it is not explained by any candidate "
                          "effect).")
                  + floor_caveat(d.context.noise, ratio),
              "", "## Residual tests", ""]
    lines += _tests_section(d.analysis_before, "Plain model")
    lines += _tests_section(d.analysis_after, "Final model")
    lines += ["## Steps", "",
              "Each candidate effect, strongest evidence first, was added and the beads "
              "judged again; it is kept when the held-out error (or the excess chi-square "
              "per degree of freedom, which also sees the faint wings and the background) "
              "drops by at least the required fraction with a bootstrap probability `p` of "
              "no drop below the limit, and neither gets worse by that fraction. The "
              "held-out error and chi2/dof columns are those of the model before and after "
              "the step on the same beads (the plain model's informative beads that both "
              "judge), and the error drop is theirs: every step starts where the last kept "
              "one ended, and a rejected step leaves the model as it was. The excess chi2 "
              "drop is that of the beads' chi2/dof - 1, each winsorised at the 95th "
              "percentile, against at least its own uncertainty.", "",
              *_md_table(STEP_COLUMNS, steps_table(d)), ""]
    lines += ["## Noise model", "", noise_text(d.context.noise), "",
              "## Figures", "",
              f"Residual maps: each bead's held-out excess error (relative residual energy "
              f"minus its noise floor) as a disk at its place in the field; colour from 0 "
              f"(dark purple) to {_num(fig['map_limit'], '.3g')} or more (yellow), the same "
              "for both; grey: no bead.", "",
              "| plain model | final model |", "|---|---|",
              "| ![residual map, plain model](residual_map_before.png) "
              "| ![residual map, final model](residual_map_after.png) |", "",
              "Mean normalised residual patch over the beads: black negative, grey zero, "
              f"white positive, +-{_num(fig['mean_limit'], '.3g')} noise sd for both.", "",
              "| plain model | final model |", "|---|---|",
              "| ![mean residual, plain model](mean_residual_before.png) "
              "| ![mean residual, final model](mean_residual_after.png) |", "",
              f"Normalised residual patches of the 16 worst beads (+-{PATCH_LIMIT:g} noise "
              "sd).", "",
              "| plain model | final model |", "|---|---|",
              "| ![worst residual patches, plain model](residual_patches_before.png) "
              "| ![worst residual patches, final model](residual_patches_after.png) |", "",
              "## Terms", "",
              f"- *{metric.NAME}*: {metric.DEFINITION} ({metric.UNIT}).",
              f"- *noise floor*: {metric.FLOOR_DEFINITION}.",
              "- *chi2/dof*: chi-square per degree of freedom under the noise model (1 for a "
              "model that explains everything but the noise).",
              "- *evidence*: strongest z / threshold of the tests that point at the effect "
              "(above 1 is significant).",
              "- *excess chi2*: chi-square per degree of freedom minus 1, per bead.",
              "- *p*: bootstrap probability over beads that the error did not drop.", "",
              "Every number is in `report.json` (fields documented in napari-psfspace's "
              "`docs/report-format.md`).", ""]
    return "\n".join(lines)


# ------------------------------------------------------------------ JSON
def to_jsonable(obj: Any) -> Any:
    """A copy with numpy types as Python ones, tuples as lists, NaN / inf as None."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj


def _fwhm_dict(op, pixel_size: float | None) -> dict:
    """The model's lateral FWHM at the centre and the corners (Gaussian fits with an
    offset), pixels and, where the pixel size is known, nm."""
    out = {}
    for place, m in field_fwhm(op).items():
        row = {k: m[k] for k in ("row", "col", "fwhm_lateral", "fwhm_row", "fwhm_col",
                                 "fwhm_major", "fwhm_minor", "ellipticity", "angle")}
        if pixel_size:
            nm, _ = in_units(m, (pixel_size, pixel_size))
            row.update({f"{k}_nm": nm[k] for k in ("fwhm_lateral", "fwhm_row", "fwhm_col",
                                                   "fwhm_major", "fwhm_minor")})
        out[place] = row
    return out


def report_dict(diagnosis, *, image_name: str = "image", pixel_size: float | None = None,
                extra: dict | None = None) -> dict:
    """The content of report.json (docs/report-format.md), JSON-safe."""
    d = diagnosis
    r = float(d.context.psf_radius)
    op = d.operator
    run = {"image": str(image_name), "image_shape": list(d.context.image.shape),
           "psf_radius_px": r, "psf_radius_um": r * pixel_size if pixel_size else None,
           "pixel_size_um": pixel_size, "software": "napari-psfspace",
           "version": __version__,
           "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           **(extra or {})}
    out = {
        "format": REPORT_FORMAT, "version": REPORT_VERSION, "run": run,
        **d.to_dict(),
        "relative_drop": (1 - d.error_after / d.error_before) if d.error_before else None,
        "beads_before": d.crossfit_before.summary(),
        "beads_after": d.crossfit_after.summary(),
        "effects": _effect_descriptions(d),
        "model": {"n_psf": int(op.n_psf), "psf_size": int(op.psf_size),
                  "shape": list(op.shape),
                  "n_beads_used": op.metadata.get("n_beads_used"),
                  "field_model": op.metadata.get("field_model"),
                  "field_model_reason": op.metadata.get("field_model_reason"),
                  "bead_correction": op.metadata.get("bead_correction"),
                  "denoise": op.metadata.get("denoise"),
                  "motion": op.metadata.get("motion"),
                  "fwhm": _fwhm_dict(op, pixel_size)},
        "figures": dict(FIGURES),
    }
    return to_jsonable(out)


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
    from .figure import write_figure

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{os.fspath(out)!r} is a file: give a folder for the report.")
    out.mkdir(parents=True, exist_ok=True)
    data = report_dict(diagnosis, image_name=image_name, pixel_size=pixel_size, extra=extra)
    fig = figure_arrays(diagnosis)
    px = pixel_size or diagnosis.operator.metadata.get("pixel_size_um")
    for when, which in (("before", "plain"), ("after", "final")):
        write_figure(out / f"residual_map_{when}.png", fig[f"map_{when}"],
                     title=f"Held-out excess error, {which} model",
                     unit="fraction of energy", limits=(0.0, fig["map_limit"]),
                     pixel_size=px * fig["cell_size"] if px else None,
                     note="each bead's error less its noise floor; grey: no bead")
        write_figure(out / f"mean_residual_{when}.png", fig[f"mean_{when}"],
                     title=f"Mean residual, {which} model", unit="noise sd",
                     limits=(-fig["mean_limit"], fig["mean_limit"]), cmap="grey",
                     pixel_size=px, size=256)
        write_figure(out / f"residual_patches_{when}.png", fig[f"patches_{when}"],
                     title=f"Residuals of the worst beads, {which} model",
                     unit="noise sd", limits=(-PATCH_LIMIT, PATCH_LIMIT), cmap="grey")
    text = json.dumps(data, indent=2, allow_nan=False)
    atomic_write(out / "report.json", lambda fh: fh.write(text + "\n"), mode="w",
                 encoding="utf-8")
    md = report_markdown(diagnosis, data["run"], fig)
    path = out / "report.md"
    atomic_write(path, lambda fh: fh.write(md), mode="w", encoding="utf-8")
    return path
