"""Checks every diagnosis in the suite must pass: its figures form one chain."""

from __future__ import annotations

import math

import pytest


def assert_figures_chain(d) -> None:
    """Before, after and the drop of every step are one quantity, and they chain.

    Each step's ``error_before`` is the current model's error (the baseline's, then the
    last kept step's ``error_after``) when measured on the same beads; a correction
    before the fit (hot pixels) ends where the baseline starts; ``improvement`` is
    ``1 - after / before``; the headline figures are the first and the last model's; a
    step that could not be compared says so and is not kept.
    """
    base = d.steps[0]
    assert base.effect is None and base.error_before == base.error_after
    current, n_current = base.error_after, base.n_beads
    if d.n_beads == base.n_beads:
        assert d.error_before == pytest.approx(base.error_before, rel=1e-12)
    for s in d.steps[1:]:
        if s.stage == "before the fit":  # the baseline is its after; rejected: its before
            if s.n_beads == base.n_beads:
                assert s.error_after == pytest.approx(base.error_before, rel=1e-12)
            if not s.accepted:
                current, n_current = s.error_before, s.n_beads
            continue
        if s.n_beads == n_current:
            assert s.error_before == pytest.approx(current, rel=1e-12), s.effect
        if math.isfinite(s.improvement):
            assert s.improvement == pytest.approx(1 - s.error_after / s.error_before,
                                                  rel=1e-9, abs=1e-12), s.effect
        else:
            assert not s.accepted, s.effect
        if s.accepted:
            current, n_current = s.error_after, s.n_beads
    if d.n_beads == n_current:
        assert d.error_after == pytest.approx(current, rel=1e-12)
    v = d.verdict
    assert math.isnan(v.ratio) or v.ratio == pytest.approx(d.error_after / d.noise_floor)
