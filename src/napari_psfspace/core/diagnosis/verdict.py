"""The verdict of a diagnosis: does the model explain its own held-out beads?

A report must not hide a bad fit behind "no effect was found": when the final model's
held-out error is many times what noise alone leaves, that comes first, with what was
tested and what is left to look at. :func:`verdict` reads a
:class:`~napari_psfspace.core.diagnosis.loop.Diagnosis` and returns a :class:`Verdict`
whose ``headline`` the report, the command line and the widget all print first.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Error / noise floor at or below which the model explains its beads (noise aside).
EXPLAINED_RATIO = 1.5
#: Above this ratio the model does not explain its own held-out beads.
UNEXPLAINED_RATIO = 5.0
#: Below this ratio the error is under what noise alone leaves: the noise model
#: overstates the image's noise. An exact model's beads scatter about their floor with
#: a standard deviation near 0.2 (tests/test_residuals.py), so the mean over 20 beads
#: or more has a standard error of at most 0.045, and 0.85 lies 3.3 of them below 1.
BELOW_FLOOR_RATIO = 0.85

#: What a significant residual test says, in a microscopist's words, for the tests that
#: no candidate effect of the diagnosis answers.
TEST_MEANING = {
    "trend_amplitude": "the error changes with the beads' brightness (faint detections "
                       "that are not beads, beads of different sizes, or a detector that "
                       "is not linear)",
    "trend_background": "the error changes with the local background (structure under "
                        "the beads, or beads on a bright background)",
    "trend_subpixel": "the error changes with the beads' sub-pixel position "
                      "(undersampled PSFs, or centring)",
    "trend_neighbour": "the error grows near other detections (neighbours inside the "
                       "patches)",
    "trend_radius": "the error grows across the field (a field that varies more than "
                    "the model follows)",
    "trend_row": "the error changes along the rows (a field that varies more than the "
                 "model follows)",
    "trend_column": "the error changes along the columns (a field that varies more than "
                    "the model follows)",
    "mean_residual": "a residual common to all beads (the basis misses part of the PSF)",
    "coherent_residual": "a residual pattern shared by many beads",
}


@dataclass(frozen=True)
class Verdict:
    """How well the final model explains its held-out beads.

    Attributes
    ----------
    level : str
        "explained" (error at most :data:`EXPLAINED_RATIO` times the noise floor),
        "partly explained" (up to :data:`UNEXPLAINED_RATIO`) or "not explained".
    ratio : float
        Held-out error over the noise floor (NaN when either is unknown).
    headline : str
        One sentence, the first line of every report.
    tested : list of str
        The candidate effects tried.
    unanswered : list of str
        Significant residual tests of the final model that no candidate effect answers
        (or whose candidate was tried and not kept), with what each means.
    hints : list of str
        What to look at when the model does not explain its beads.
    """

    level: str
    ratio: float
    headline: str
    tested: list[str] = field(default_factory=list)
    unanswered: list[str] = field(default_factory=list)
    hints: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"level": self.level, "ratio": self.ratio, "headline": self.headline,
                "tested": list(self.tested), "unanswered": list(self.unanswered),
                "hints": list(self.hints)}


def saturation_sentence(diagnosis) -> str:
    """One sentence when detections have clipped pixels in their cores: how many, the
    level, and what became of the saturation effect; empty otherwise."""
    d = diagnosis
    rec = (d.options or {}).get("saturation") or {}
    n = int(rec.get("beads") or 0)
    if n == 0:
        return ""
    tried = [s for s in d.steps if s.effect == "saturation"]
    if any(s.accepted for s in tried):
        fate = "the saturation effect was added"
    elif tried:
        fate = "the saturation effect was tried and not kept"
    else:
        fate = "the saturation effect was not tried"
    return (f"Saturation: {n} of {rec.get('detections', '?')} detections have clipped "
            f"pixels in their cores (level {rec.get('level', float('nan')):g}, "
            f"{rec.get('pixels', 0)} pixels); {fate}.")


def verdict(diagnosis) -> Verdict:
    """The verdict of a :class:`~napari_psfspace.core.diagnosis.loop.Diagnosis`."""
    from .effects import REGISTRY

    d = diagnosis
    err, floor = float(d.error_after), float(d.noise_floor)
    ratio = err / floor if np.isfinite(err) and np.isfinite(floor) and floor > 0 else np.nan
    # candidate effects of the loop (corrections before and after the fit are steps too)
    tried = [s.effect for s in d.steps if s.effect and s.stage == "effect"]
    answered = {t for name in REGISTRY for t in REGISTRY[name].tests}
    kept_tests = {t for s in d.steps if s.effect and s.accepted for t in s.tests}
    unanswered = []
    for t in d.analysis_after.significant():
        if t.name in kept_tests:
            continue
        effects = [n for n in REGISTRY if t.name in REGISTRY[n].tests]
        considered = (d.options or {}).get("effects")
        if t.name in answered and considered is not None and not any(
                e in considered for e in effects):
            why = f"its candidate(s) {', '.join(effects)} not among the effects considered"
        elif t.name in answered:
            why = (f"its candidate(s) {', '.join(effects)} tried and not kept"
                   if any(e in tried for e in effects) else
                   f"its candidate(s) {', '.join(effects)} not applicable here")
        else:
            why = "no candidate effect answers it"
        meaning = TEST_MEANING.get(t.name, "")
        unanswered.append(f"{t.name} (z {t.z:.3g}, threshold {t.threshold:.3g}; {why})"
                          + (f": {meaning}" if meaning else ""))
    n_tests = len(d.analysis_before.tests)
    what = (f"{n_tests} residual tests and {len(tried)} candidate effect(s)"
            + (f" ({', '.join(tried)})" if tried else ""))
    on = f" on {d.n_beads} beads" if getattr(d, "n_beads", 0) else ""
    if not np.isfinite(ratio):
        level = "unknown"
        headline = (f"Verdict: not measured: the held-out error ({err:.4g}) or its noise "
                    f"floor ({floor:.4g}) is unknown.")
    elif ratio <= EXPLAINED_RATIO:
        level = "explained"
        headline = (f"Verdict: the model explains its held-out beads{on}: error {err:.4g}, "
                    f"{ratio:.3g} times the noise floor {floor:.4g}.")
    elif ratio <= UNEXPLAINED_RATIO:
        level = "partly explained"
        headline = (f"Verdict: the model explains most of its held-out beads{on}, not all: "
                    f"error {err:.4g} is {ratio:.3g} times the noise floor {floor:.4g}; "
                    f"tested {what}.")
    else:
        level = "not explained"
        headline = (f"Verdict: THE MODEL DOES NOT EXPLAIN ITS OWN HELD-OUT BEADS{on}: error "
                    f"{err:.4g} is {ratio:.3g} times the noise floor {floor:.4g}, after "
                    f"testing {what}. Do not use it before looking at its PSFs and the "
                    "worst residual patches.")
    hints = []
    if np.isfinite(ratio) and ratio < BELOW_FLOOR_RATIO:
        source = (getattr(d, "noise_source", "") or "not recorded").split(" (")[0]
        headline += (f" The error is below its noise floor: the noise model ({source}) "
                     "overstates this image's noise, so the floor and this verdict are "
                     "indicative only.")
        hints.append("give the camera's gain, offset and read noise (or a dark frame's) "
                     "to judge the model against the image's own noise")
    sat = saturation_sentence(d)
    if sat:
        headline += " " + sat
    if level in ("partly explained", "not explained"):
        model = d.operator.metadata or {}
        used = model.get("n_beads_used")
        if used is not None and used < 10:
            hints.append(f"only {used} beads were used: check each one in the patch "
                         "review (a faint detection, a bead with a neighbour or on "
                         "structure decides much of a few-bead model)")
        if unanswered:
            hints.append("significant residual tests left: " + "; ".join(unanswered))
        if model.get("field_model") in ("shift-invariant", "affine"):
            hints.append(f"the field model is {model['field_model']}: "
                         + str(model.get("field_model_reason", "")))
        hints.append("check the PSF radius against the beads' extent: a radius smaller "
                     "than the PSF leaves its wings in the residual, a larger one takes "
                     "in neighbours and background")
    return Verdict(level, float(ratio), headline, tried, unanswered, hints)


__all__ = ["BELOW_FLOOR_RATIO", "EXPLAINED_RATIO", "UNEXPLAINED_RATIO", "Verdict",
           "saturation_sentence", "verdict"]
