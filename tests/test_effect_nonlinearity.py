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
