"""Nonlinear detector response: fitted from the beads and linearised."""

import numpy as np
import pytest

from napari_psfspace import simulate_beads
from napari_psfspace.core.diagnosis.effects.nonlinearity import Response, linearise
from napari_psfspace.core.diagnosis.loop import diagnose


def test_response_round_trip_and_slope():
    r = Response(0.2, 4000.0, 100.0)
    x = np.linspace(100, 4100, 50)
    assert np.allclose(r.inverse(r.forward(x)), x)
    h = 1e-3
    assert np.allclose(r.slope(x), (r.forward(x + h) - r.forward(x - h)) / (2 * h))
    assert np.array_equal(linearise(x, 0.0, 4000.0, 100.0), x)
    # expansive responses invert too
    e = Response(-0.1, 4000.0, 100.0)
    assert np.allclose(e.inverse(e.forward(x)), x)


@pytest.mark.parametrize("c", [0.3])
def test_compressive_response_is_found_and_lowers_the_error(c):
    # aberration-free field: the model error is at the noise floor, so the compression
    # of the bright beads' cores is what is left
    image, truth = simulate_beads((640, 640), 70, aberrations="none", seed=2,
                                  effects={"nonlinearity": c})
    d = diagnose(image, psf_radius=truth.psf_radius)
    assert "nonlinearity" in d.added
    step = next(s for s in d.steps if s.effect == "nonlinearity")
    # measured: 0.0020 -> 0.0017 (-12 %), excess chi2/dof -51 %
    assert step.error_after < 0.93 * step.error_before
    # the fitted coefficient, expressed against the recorded maximum, is near the truth:
    # c_true * x_ref / (e_ref * gain) = 0.21; measured 0.16
    x_ref = step.params["x_ref_adu"]
    c_true = c * x_ref / (truth.effects["nonlinearity_reference"] * truth.gain)
    assert 0.5 * c_true < step.params["c"] < 1.3 * c_true


def test_linear_detector_adds_nothing():
    image, truth = simulate_beads((640, 640), 70, aberrations="none", seed=2)
    d = diagnose(image, psf_radius=truth.psf_radius, effects=["nonlinearity"])
    assert d.added == []


@pytest.mark.parametrize("slope, accepted", [(45.0, True), (-45.0, False)])
def test_only_a_compressive_response_is_fitted(monkeypatch, slope, accepted):
    """As recorded the trend reads z -3.65. Where a compressive response (c > 0)
    cancels it, that is fitted; where only an expansive one would (a vignetted scene of
    the power bench with no response: cancelled at c -0.08), the fit refuses."""
    from types import SimpleNamespace

    from napari_psfspace.core.diagnosis.effects import nonlinearity as nl

    monkeypatch.setattr(nl, "_core_trend", lambda res, c, *a: -3.65 + slope * c)
    monkeypatch.setattr(nl, "round_beads", lambda res, **kw: np.ones(3, bool))
    res = SimpleNamespace(data=np.zeros((3, 9, 9)), informative=np.ones(3, bool))
    res.take = lambda use: res
    ctx = SimpleNamespace(image=np.full((32, 32), 100.0), pixel_mask=np.zeros((32, 32), bool),
                          noise=SimpleNamespace(offset=90.0), psf_radius=3.0)
    ctx.image[16, 16] = 4000.0
    fit = nl.Nonlinearity().fit
    if accepted:
        assert fit(ctx, SimpleNamespace(residuals=res))["c"] == pytest.approx(3.65 / 45, abs=1e-3)
    else:
        with pytest.raises(ValueError, match="not a quadratic response"):
            fit(ctx, SimpleNamespace(residuals=res))
