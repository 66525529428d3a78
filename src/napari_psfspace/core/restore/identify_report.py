"""What an identification says about itself: its bounds, its warnings, its error band.

An operator identified from a few beads (:func:`~.identify.identify_operator`) is only as
good as the family's model of the image's condition and as the beads that placed it.
Three things can go wrong, and each is said in one warning that names where more beads
would help:

- the family does not explain the clicked beads (their median error beyond their noise
  above :func:`warn_bound`, from the family's own error on its held-out beads): a
  condition it never learnt, another microscope, or beads that are not single points;
- a clicked bead disagrees with the others (:mod:`.bead_check`): it is left out;
- the beads leave the operator undetermined: the error band's upper end above
  :data:`SPREAD_RATIO` times the bound.

The error band (:func:`error_band`) is the 90 % range of the identified operator's PSF
error over the field: the error the posterior spread predicts, scaled by the quantiles
of the ratio of actual to predicted error measured when the family was learnt (each of
its images left out and identified from a few of its beads), its high end with the
family's own error on beads it never saw.
"""

from __future__ import annotations

import numpy as np

from ..family.result import OperatorFamily
from ..model.heldout import beyond_noise

#: The warning's bound on the identified operator's error on the clicked beads, beyond
#: their noise (relative l2 of the PSF; ``model_error``, measured on the beads it was
#: fitted to), in units of the family's own error on beads it never saw (the median
#: over its images of the same measure on their held-out beads).
WARN_RATIO = 1.1
#: The bound without held-out figures (a family learnt with ``holdout=None``), and its
#: floor otherwise.
WARN_MODEL_ERROR = 0.1
WARN_FLOOR = 0.03
#: The warning's bound on the error band's upper end, in units of :func:`warn_bound`.
SPREAD_RATIO = 3.0


class IdentificationWarning(UserWarning):
    """The family does not explain the beads an operator was identified from, one of
    them disagrees with the others, or they leave part of the field undetermined."""


def family_model_error(family: OperatorFamily) -> float | None:
    """The family's error beyond the noise on beads it never saw: the median over its
    images of ``sqrt(residual^2 - floor^2)`` of their held-out beads (None without)."""
    held = [h for h in family.metadata.get("heldout") or []
            if h.get("n_beads") and h.get("residual_mean") is not None]
    if not held:
        return None
    return float(np.median([beyond_noise(h["residual_mean"], h["noise_floor_mean"])
                            for h in held]))


def warn_bound(family: OperatorFamily) -> float:
    """The ``model_error`` above which :func:`~.identify.identify_operator` warns."""
    ref = family_model_error(family)
    return WARN_MODEL_ERROR if ref is None else max(WARN_FLOOR, WARN_RATIO * ref)


def error_band(family: OperatorFamily, predicted: float) -> tuple[float, float] | None:
    """The 90 % band of the identified operator's PSF error over the field's central
    part (relative l2, as judged up to a sub-pixel shift), from the error its spread
    ``predicted`` (None: the family holds no calibration, ``metadata["dimensions"]
    ["band"]``).

    Its low end is the identification's part alone: ``predicted`` scaled by the
    calibration's low quantile. Its high end adds, to the high quantile's, the family's
    own error at most: what its held-out beads show beyond their noise
    (:func:`family_model_error`, which also holds each bead's centring jitter; at least
    what the beads' noise gives its fields, ``metadata["dimensions"]["floor"]``). The
    calibration is made on images inside the conditions the family learnt: beyond them
    the band says nothing, and the miss warning speaks instead.
    """
    dims = family.metadata.get("dimensions") or {}
    band = dims.get("band")
    if not band or not np.isfinite(predicted):
        return None
    high_floor = max(family_model_error(family) or 0.0, float(dims.get("floor") or 0.0))
    return (float(band["low"] * predicted),
            float(np.hypot(band["high"] * predicted, high_floor)))


def where_text(point) -> str:
    """``(row, column)`` of a position, pixels."""
    y, x = point
    return f"({y:.0f}, {x:.0f})"


def miss_warning(model_error: float, bound: float) -> str | None:
    """Why the family does not explain the clicked beads (None: it does)."""
    if model_error <= bound:
        return None
    return (f"the family does not explain the clicked beads: its operator misses them "
            f"by {model_error:.2f} of their PSF beyond their noise (bound {bound:.2g}, "
            "from the family's error on its own held-out beads); it may be far from "
            "this image's (a condition the family did not learn, another microscope, "
            "or beads that are not single points): click more beads, or learn a "
            "family that covers this condition")


def left_out_warning(positions: np.ndarray, scores: np.ndarray) -> str | None:
    """Which clicked beads were left out, and why (None: none)."""
    if not len(positions):
        return None
    named = ", ".join(f"{where_text(p)} ({s:.0f}x)" for p, s in zip(positions, scores,
                                                                     strict=True))
    one = len(positions) == 1
    return (f"the clicked bead{'' if one else 's'} at {named} disagree{'s' if one else ''} "
            "with the others (its PSF misses what they predict there by that many times "
            "the expected error) and, unlike a single bead's, its shape is not one the "
            f"family's PSFs take: {'it was' if one else 'they were'} left out (a pair of "
            "beads too close to resolve, a saturated bead, or one on a structure?)")


def spread_warning(band: tuple[float, float] | None, mean_spread: float,
                   bound: float) -> str | None:
    """Why the clicked beads leave the operator undetermined (None: they do not): the
    band's upper end (or, without a band, the mean spread) above :data:`SPREAD_RATIO`
    times ``bound``."""
    top = mean_spread if band is None else band[1]
    if not np.isfinite(top) or top <= SPREAD_RATIO * bound:
        return None
    return (f"the clicked beads leave the operator undetermined: its PSF may be off by up "
            f"to {top:.2f} of its norm over the field (bound {SPREAD_RATIO * bound:.2g}, "
            f"{SPREAD_RATIO:g}x the family's error on its own held-out beads)")


def more_beads_text(where) -> str:
    """Where one more bead would help most."""
    return f"one more bead would help most near {where_text(where)}"
