"""Corrections a diagnosis makes outside its loop of effects, each as a named step.

- **Hot pixels** (before the fit): pixels narrower than the optics can form, found at
  detection (:func:`~napari_psfspace.core.beads.spikes.find_spikes`), are masked and
  inpainted. The step's statistic is the spikes the finder reads in the image before and
  after; its held-out figures are those of the plain model on the image as recorded and
  on the cleaned one, the same beads and the same noise model. Kept when the spikes are
  gone and the held-out error is not worse beyond one standard error.
- **Motion** (after the fit): a smear common to every bead
  (:mod:`~napari_psfspace.core.model.motion`). No held-out bead can see it (every bead
  carries it, and the model learns it with them), so it is a one-parameter physical
  effect judged on its own test: found, and divided out of the final operator when the
  user asks (``remove_motion``). Dividing a smear out leaves its zero line, where the
  beads carry no signal, so its own test cannot read the correction (``after`` None);
  the step says so.
"""

from __future__ import annotations

import numpy as np

from ..beads.spikes import find_spikes, is_integer_valued, pixel_noise_sd
from .comparison import compare
from .steps import Step, statistic

#: What each correction is, in a microscopist's words (reports).
CORRECTIONS = {
    "hot_pixels": "hot pixels and cosmic rays (single pixels narrower than the optics can "
                  "form) masked and inpainted before the fit",
    "motion": "a smear common to every bead (stage or sample motion during the exposure) "
              "divided out of the final operator",
}

#: A correction may leave the held-out error higher by at most this many standard errors
#: of the paired difference (the noise of the comparison itself).
NOT_WORSE_SE = 1.0


def not_worse(cmp: dict) -> bool:
    """The held-out error after is at most :data:`NOT_WORSE_SE` standard errors of the
    paired difference above the error before (no comparison: not worse)."""
    if "note" in cmp or not np.isfinite(cmp.get("error_after", np.nan)):
        return True
    return bool(cmp["error_after"] <= cmp["error_before"] + NOT_WORSE_SE * cmp["error_se"])


def spike_count(image: np.ndarray, raw: np.ndarray) -> int:
    """Pixels narrower than the optics can form in ``image`` (hot pixels, cosmic rays),
    read as detection reads the recorded image ``raw`` (its noise and integer steps)."""
    integer = is_integer_valued(raw)
    sd = pixel_noise_sd(raw, integer=integer)
    return int(len(find_spikes(image, noise_sd=sd, integer=integer)))


def hot_pixel_step(before_cf, after_cf, noise, reference, *, informative: bool,
                   spikes_before: int, spikes_after: int) -> Step:
    """The hot-pixel step from the plain model's cross-fits on the image as recorded
    (``before_cf``) and with the hot pixels masked (``after_cf``), judged under one noise
    model."""
    cmp = compare(before_cf, after_cf, noise, reference=reference, informative=informative)
    stat = statistic("spikes", spikes_before, spikes_after, 0.0)
    ok = bool(stat["significant_before"] and not stat["significant_after"] and not_worse(cmp))
    return Step(effect="hot_pixels", evidence=float(spikes_before), tests=["spikes"],
                error_before=cmp["error_before"], error_after=cmp["error_after"],
                chi2_before=cmp["chi2_before"], chi2_after=cmp["chi2_after"],
                improvement=float(cmp["improvement"]), p_no_drop=float(cmp["p_no_drop"]),
                accepted=ok, params={"count": int(spikes_before), "_comparison": cmp},
                stage="before the fit", statistic=stat)


def motion_step(record: dict, removed: bool, error: float, chi2: float, n_beads: int) -> Step:
    """The motion step from the final model's motion record (``metadata["motion"]`` of a
    smear found); ``removed``: divided out of the final operator. ``error``, ``chi2``:
    the final model's held-out figures, which the correction leaves as they are."""
    from ..model.motion import MAX_EDGE_RATIO, MIN_DIP_Z

    # the test's own evidence: a zero line's depth in standard errors over its threshold,
    # or (a zero too near the optics' cutoff) the threshold over the smear's fall
    z, ratio = record.get("dip_z"), record.get("dip_ratio")
    evidence = (float(z) / MIN_DIP_Z if z is not None
                else MAX_EDGE_RATIO / max(float(ratio), 1e-12))
    stat = statistic("motion", evidence, None, 1.0,
                     note="the test's evidence over its threshold; a smear's zero line "
                          "carries no signal: dividing the smear out leaves it, so the "
                          "test cannot read the correction; a one-parameter physical "
                          "effect, kept on its own evidence")
    params = {k: record.get(k) for k in ("length_px", "angle_deg", "dip_ratio", "dip_z",
                                         "reason")}
    params["n_beads"] = int(n_beads)
    params["removed"] = bool(removed)
    if not removed:
        params["note"] = ("found and kept in the model, right for this exposure; "
                          "remove_motion divides it out (the sample was still)")
    return Step(effect="motion", evidence=evidence, tests=["motion"],
                error_before=error, error_after=error, chi2_before=chi2, chi2_after=chi2,
                improvement=0.0, p_no_drop=1.0, accepted=bool(removed), params=params,
                stage="after the fit", statistic=stat)
