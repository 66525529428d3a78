"""Non-uniform illumination: found from the beads' brightness, held-out photometry drops."""

import numpy as np

from napari_psfspace import simulate_beads
from napari_psfspace.core.diagnosis.loop import diagnose
from napari_psfspace.core.diagnosis.photometry import throughput_at


def test_illumination_is_added_and_lowers_the_photometric_error():
    # beads of similar brightness (+-14 %) under an illumination falling to ~0.63
    image, truth = simulate_beads((640, 640), 70, aberrations="moderate", seed=0,
                                  amplitude=(3e4, 4e4), effects={"illumination": 0.5})
    d = diagnose(image, psf_radius=truth.psf_radius,
                 effects=["illumination", "basis_size", "field_smoothing"])
    assert "illumination" in d.added
    step = next(s for s in d.steps if s.effect == "illumination")
    cmp = step.params["_comparison"]
    # measured: held-out squared log error 0.029 -> 0.0105 (-64 %), p < 0.001
    assert cmp["photometric_after"] < 0.6 * cmp["photometric_before"]
    # its own test, read on the held-out amplitude ratios, goes from significant to not
    # (measured: z 7.7 before, below 0 after)
    assert step.statistic["significant_before"] and step.statistic["significant_after"] is False
    # the PSF shapes are unchanged by it
    assert abs(step.error_after - step.error_before) < 1e-12
    # the operator's throughput follows the true illumination (measured r = 0.97)
    coef = d.operator.metadata["throughput"]["coefficients"]
    est = throughput_at(coef, truth.positions, image.shape)
    true = truth.effects["illumination_factors"]
    assert np.corrcoef(np.log(est), np.log(true))[0, 1] > 0.85
    # the operator passes the throughput: a uniform sample looks dimmer where the
    # illumination is (truth: 0.63 of the centre at the darkest corner)
    flat = d.operator.apply(np.ones(image.shape, np.float32))
    dark = np.unravel_index(np.argmin(truth.effects["illumination_map"]), image.shape)
    cy, cx = np.round(truth.effects["illumination_centre"]).astype(int)
    assert flat[dark] < 0.8 * flat[cy, cx]


def test_uniform_illumination_adds_nothing():
    image, truth = simulate_beads((640, 640), 70, aberrations="moderate", seed=0,
                                  amplitude=(3e4, 4e4))
    d = diagnose(image, psf_radius=truth.psf_radius, effects=["illumination"])
    assert d.added == []
    assert not d.analysis_before.tests["amplitude_field"].significant
