"""One step of a diagnosis: the baseline, a correction made before the fit, an effect the
loop tried, or a correction of the final model, each with its figures before and after.

A step's held-out figures (``error_*``, ``chi2_*``) are means over the same beads before
and after it; its ``statistic`` is its own test's value before and after, where the
step has a test of its own (hot pixels: the spikes left in the image; an effect: the
strongest of its residual tests; motion: the smear's zero line).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: Where a step acts: on the image before any model is fitted, inside the loop (an
#: effect added to the model and judged by held-out beads), or on the final model.
STAGES = ("before the fit", "effect", "after the fit")


@dataclass
class Step:
    """One candidate effect tried by the loop (or the baseline, ``effect=None``).

    ``error_before`` / ``error_after`` and ``chi2_before`` / ``chi2_after`` are those of
    the model before and after the step on the same beads (the plain model's
    informative beads that both judge, :func:`~.comparison.paired_beads`), and
    ``improvement`` is ``1 - error_after / error_before`` on them: one quantity. A step
    starts where the last kept one ended (on the same beads, the same figure). NaN
    ``improvement``: fewer than :data:`~.comparison.MIN_PAIRED` beads to compare.

    ``stage`` is one of :data:`STAGES`. ``statistic`` (or None) is the step's own test:
    ``test``, ``before``, ``after`` and ``threshold`` (the test's units), and
    ``significant_before`` / ``significant_after``; ``after`` None where the test cannot
    read the correction (``note`` says why).
    """

    effect: str | None
    evidence: float
    tests: list[str]
    error_before: float
    error_after: float
    chi2_before: float
    chi2_after: float
    improvement: float
    p_no_drop: float
    accepted: bool
    params: dict = field(default_factory=dict)
    stage: str = "effect"
    statistic: dict | None = None

    @property
    def n_beads(self) -> int:
        """The beads the step's figures are means over."""
        p = self.params or {}
        return int(p.get("_comparison", {}).get("n_beads", p.get("n_beads", 0)))

    def to_dict(self) -> dict:
        def short(v):
            if isinstance(v, list) and len(v) > 20:
                return f"<{len(v)} values>"
            return v

        return {"effect": self.effect, "stage": self.stage, "evidence": self.evidence,
                "tests": self.tests, "statistic": self.statistic,
                "error_before": self.error_before, "error_after": self.error_after,
                "chi2_dof_before": self.chi2_before, "chi2_dof_after": self.chi2_after,
                "improvement": self.improvement, "p_no_drop": self.p_no_drop,
                "accepted": self.accepted,
                "params": {k: short(v) for k, v in self.params.items()}}


def statistic(test: str, before: float, after: float | None, threshold: float, *,
              note: str | None = None) -> dict:
    """The record of a step's own test (see :class:`Step`); ``after`` None: not read."""
    def num(v):
        return None if v is None or not math.isfinite(float(v)) else float(v)

    out = {"test": test, "before": num(before), "after": num(after),
           "threshold": float(threshold),
           "significant_before": bool(num(before) is not None and before > threshold),
           "significant_after": (None if num(after) is None else bool(after > threshold))}
    if note:
        out["note"] = note
    return out
