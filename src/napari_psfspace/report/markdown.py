"""``report.md``: the diagnosis in words and tables, for a microscopist.
"""

from __future__ import annotations

import math

from ..core.common.measures import field_fwhm, fwhm_line
from ..core.diagnosis import metric
from ..core.model.fewbeads import one_psf_note
from .figures import PATCH_LIMIT

#: Columns of :func:`steps_table`.
STEP_COLUMNS = ("effect", "stage", "evidence", "tests", "own test", "held-out error", "chi2/dof",
                "paired error drop", "p", "paired excess chi2 drop", "p (chi2)",
                "photometric drop", "decision")

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
               "and misfit / noise are only indicative")
    plain = "" if d.heldout is None else f"plain model: {d.heldout.line()}\n"
    return (f"{v.headline}\n{hot}{plain}added: {added}\n"
            f"held-out error {_num(d.error_before)} -> {_num(d.error_after)} on "
            f"{d.n_beads} beads (noise floor {_num(d.noise_floor)}); misfit / noise "
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

def effect_descriptions(diagnosis) -> dict[str, str]:
    from ..core.diagnosis.corrections import CORRECTIONS
    from ..core.diagnosis.effects import REGISTRY

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
    descr = effect_descriptions(d)
    px = run.get("pixel_size_um")
    lines = [f"# PSF model diagnosis: {run['image']}", "",
             f"napari-psfspace {run['version']}, {run['date']}. Image "
             f"{run['image_shape'][0]} x {run['image_shape'][1]} px"
             + (f" at {px:g} µm/px" if px else "")
             + f"; PSF radius {run['psf_radius_px']:.3g} px; "
             f"{len(d.crossfit_before.residuals)} beads judged by models that did not see "
             "them (cross-fitting).", "", "## What was found", ""]
    v = d.verdict
    lines += _found(d, descr)
    lines += model_lines(d.operator.metadata)
    lines += ["", fwhm_line(field_fwhm(d.operator), px,
                               one_psf=one_psf_note(d.operator.metadata)) + "."]
    lines += _notes(d)
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
    lines += _steps_section(d)
    lines += _appendix(fig, d)
    return "\n".join(lines)


def _found(d, descr):
    """What was found: the verdict, its hints, and the effects added (or why none was)."""
    v = d.verdict
    lines = [f"**{v.headline}**", ""]
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
    return lines


def _notes(d):
    """Motion blur, vignetting, leave-one-bead-out and hot pixels, where they apply."""
    lines = []
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
    return lines


def _steps_section(d):
    """How each step is judged, and the steps' table."""
    lines = []
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
    return lines


def _appendix(fig, d):
    """The noise model, the figures and the terms."""
    lines = []
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
              "- *chi2/dof* (*misfit / noise* in the summary and the panel): chi-square per "
              "degree of freedom under the noise model (1 for a model that explains "
              "everything but the noise).",
              "- *evidence*: strongest z / threshold of the tests that point at the effect "
              "(above 1 is significant).",
              "- *excess chi2*: chi-square per degree of freedom minus 1, per bead.",
              "- *p*: bootstrap probability over beads that the error did not drop.", "",
              "Every number is in `report.json` (fields documented in napari-psfspace's "
              "`docs/report-format.md`).", ""]
    return lines


__all__ = ["floor_caveat", "model_lines", "noise_text", "own_test_text", "report_markdown",
           "STEP_COLUMNS", "steps_table", "summary_text"]
