"""Keeping an effect on its own test: the rule's cases, one at a time."""

import pytest

from napari_psfspace.core.diagnosis.acceptance import kept_by_own_test
from napari_psfspace.core.diagnosis.effects import REGISTRY
from napari_psfspace.core.diagnosis.steps import statistic

RESPONSE = REGISTRY["nonlinearity"]()  # a test of its own that reads its correction
SIZE_OF_MODEL = REGISTRY["basis_size"]()  # none: its tests are any misfit's


def _cmp(before=0.010, after=0.0101, se=0.0002, chi2=0.0):
    return {"error_before": before, "error_after": after, "error_se": se,
            "improvement": 1 - after / before, "chi2_improvement": chi2}


def _kept(eff, own, cmp, kind="photon transfer"):
    return kept_by_own_test(eff, own, cmp, kind, min_improvement=0.05)


QUIET = statistic("core_vs_amplitude", 5.0, 1.0, 3.0)


def test_kept_when_its_test_goes_quiet_and_nothing_is_worse():
    # the error rose by half a standard error of the paired difference: not worse
    assert _kept(RESPONSE, QUIET, _cmp())


@pytest.mark.parametrize("why, eff, own, cmp", [
    ("the error rose by more than one standard error", RESPONSE, QUIET,
     _cmp(after=0.0103)),
    ("the excess chi-square rose by more than min_improvement", RESPONSE, QUIET,
     _cmp(chi2=-0.28)),
    ("its test is still significant", RESPONSE,
     statistic("core_vs_amplitude", 5.0, 3.5, 3.0), _cmp()),
    ("its test was not significant to begin with", RESPONSE,
     statistic("core_vs_amplitude", 2.0, 1.0, 3.0), _cmp()),
    ("the effect has no test of its own", SIZE_OF_MODEL, QUIET, _cmp()),
    ("the beads could not be compared", RESPONSE, QUIET, {**_cmp(), "note": "too few"}),
])
def test_not_kept(why, eff, own, cmp):
    assert not _kept(eff, own, cmp), why


def test_an_assumed_noise_model_does_not_judge_the_chi_square():
    # a fallback noise model: the chi-square is only indicative, as in accept_effect
    assert _kept(RESPONSE, QUIET, _cmp(chi2=-0.28), kind="constant")


def test_an_effect_with_its_own_test_is_not_explored():
    """While a residual common to the beads is left, weaker evidence is followed too,
    but not for an effect whose own test reads it: that test must be significant."""
    from napari_psfspace.core.diagnosis.acceptance import next_effect
    from napari_psfspace.core.diagnosis.analysis import Analysis, TestResult

    class Fits:  # a cross-fit far above its noise floor
        def summary(self):
            return {"error": 0.05, "noise_floor": 0.01}

    class Ctx:
        applied = ()

    def analysis(core_z):
        return Analysis({"mean_residual": TestResult("mean_residual", 30.0, 5.0),
                         "core_vs_amplitude": TestResult("core_vs_amplitude", core_z, 3.0,
                                                         two_sided=True),
                         "trend_radius": TestResult("trend_radius", 2.0, 4.0,
                                                    two_sided=True)})

    effects = [REGISTRY["nonlinearity"](), REGISTRY["field_smoothing"]()]
    # evidence 0.6 for the response (own test) and 0.5 for the field: only the field
    chosen = next_effect(effects, set(), Ctx(), Fits(), analysis(1.8), explore=0.4)
    assert chosen is not None and chosen[1].name == "field_smoothing"
    chosen = next_effect(effects, set(), Ctx(), Fits(), analysis(3.3), explore=0.4)
    assert chosen[1].name == "nonlinearity"
