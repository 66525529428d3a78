"""Which effect the diagnosis tries next, and whether it keeps it.

An effect is tried in order of evidence (its residual tests' ``z / threshold``). It is
kept when a held-out metric drops significantly (:func:`accept_effect`), or, for an
effect with a test of its own that reads its correction
(:attr:`~.effects.base.Effect.own_evidence`), when that test goes from significant to
not while the held-out error is not worse (:func:`~.corrections.not_worse`, applied by
the loop).
"""

from __future__ import annotations

from .analysis import Analysis
from .crossfit import CrossFit
from .effects import Context, Effect
from .steps import statistic

#: Tests whose significance means a residual common to the beads is left unexplained.
EXPLAIN_TESTS = ("mean_residual", "coherent_residual")


def next_effect(candidates: list[Effect], tried: set[str], ctx: Context, cf: CrossFit,
                an: Analysis, explore: float) -> tuple[float, Effect] | None:
    """The effect to try next, with its evidence: significant evidence first; while a
    residual common to the beads remains far above the noise (mean or coherent residual
    significant, error > 1.5 x floor), weaker evidence (> ``explore``) is followed too
    (the acceptance rule decides), except for an effect with a test of its own
    (:attr:`~.effects.base.Effect.own_evidence`), tried only when that test is
    significant. None when no untried effect qualifies."""
    ranked = sorted(((e.evidence(an), e) for e in candidates
                     if e.name not in tried and e.applicable(ctx)), key=lambda t: -t[0])
    cur = cf.summary()
    unexplained = (cur["error"] > 1.5 * cur["noise_floor"]
                   and any(an.tests[t].significant for t in EXPLAIN_TESTS if t in an.tests))
    floor = 1.0 if not (explore and unexplained) else min(1.0, explore)
    # an effect whose own test reads it is tried on that test only: explored, a response
    # "explained" a model's misfit on an effect-free scene.
    ranked = [(ev, e) for ev, e in ranked if ev > (1.0 if e.own_evidence else floor)]
    return ranked[0] if ranked else None


def accept_effect(cmp: dict, noise_kind: str, evidence: float, *, min_improvement: float,
                  evident_improvement: float, max_p: float) -> bool:
    """Keep an effect: one held-out metric of the comparison drops (by the improvement
    needed, with ``p <= max_p / 2``) and none gets worse by ``min_improvement``.

    An assumed noise model (a fallback) makes the chi-square only indicative (the report
    says so): it does not decide (an effect could "explain" a constant-variance model's
    missing shot noise in bright cores). An effect its own test calls significant
    (evidence > 1) needs only ``evident_improvement`` (the effect is often a small part of
    a model's error, ``bench/bench_diagnose.py``); one only explored needs the full one.
    """
    metrics = _metrics(cmp, noise_kind)
    need = min(min_improvement, evident_improvement) if evidence > 1.0 else min_improvement
    return bool(any(cmp[f"{m}improvement"] >= need and cmp[f"{m}p_no_drop"] <= max_p / 2
                    for m in metrics)
                and none_worse(cmp, noise_kind, min_improvement=min_improvement))


def _metrics(cmp: dict, noise_kind: str) -> list[str]:
    """The held-out metrics of a comparison that decide (prefixes of its keys)."""
    metrics = [m for m in ("", "chi2_", "photometric_") if f"{m}improvement" in cmp]
    if noise_kind not in ("photon transfer", "camera"):
        metrics = [m for m in metrics if m != "chi2_"]
    return metrics


def none_worse(cmp: dict, noise_kind: str, *, min_improvement: float) -> bool:
    """No held-out metric of the comparison got worse by ``min_improvement`` (relative)."""
    return all(cmp[f"{m}improvement"] > -min_improvement for m in _metrics(cmp, noise_kind))


def kept_by_own_test(eff: Effect, own: dict | None, cmp: dict, noise_kind: str, *,
                     min_improvement: float) -> bool:
    """Keep an effect whose own test reads its correction
    (:attr:`~.effects.base.Effect.own_evidence`): that test went from significant to
    not, the held-out error is not worse beyond one standard error of the paired
    difference (:func:`~.corrections.not_worse`), and no held-out metric got worse by
    ``min_improvement`` (a wrong effect can silence a test it shares with the right one:
    a compressive response widens the bright beads as bigger beads do, and the bead-size
    correction then silences the bead-width test while the excess chi-square rises,
    ``tests/test_effect_nonlinearity.py``)."""
    from .corrections import not_worse

    return bool(eff.own_evidence and own is not None and own["significant_before"]
                and own["significant_after"] is False and not_worse(cmp)
                and "note" not in cmp
                and none_worse(cmp, noise_kind, min_improvement=min_improvement))


def own_statistic(eff: Effect, before: Analysis, after: Analysis, ctx: Context,
                  cf: CrossFit) -> dict | None:
    """The effect's strongest own test (:attr:`Effect.tests`) before and after it (read
    by :meth:`Effect.reading_after` on the model with it: context ``ctx``, cross-fit
    ``cf``)."""
    names = [t for t in eff.tests if t in before.tests]
    if not names:
        return None
    t = max(names, key=lambda n: before.tests[n].evidence)
    b = before.tests[t]
    return statistic(t, b.strength, eff.reading_after(t, after, ctx, cf), b.threshold)


def evident_tests(eff: Effect, an: Analysis) -> list[str]:
    """The effect's own residual tests that are significant."""
    return [t for t in eff.tests if t in an.tests and an.tests[t].significant]


