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
