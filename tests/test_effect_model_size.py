"""A model too small for what the beads show: a basis of too few PSFs, a field model
smoothed too much (e.g. chosen by the user), found and enlarged."""

import pytest

from napari_psfspace import simulate_beads
from napari_psfspace.core.diagnosis.loop import diagnose


@pytest.fixture(scope="module")
def strong():
    return simulate_beads((640, 640), 70, aberrations="strong", seed=1)


def test_a_basis_too_small_is_enlarged(strong):
    image, truth = strong
    d = diagnose(image, psf_radius=truth.psf_radius, n_psf=1,
                 effects=["basis_size", "field_smoothing"])
    assert d.added[0] == "basis_size"
    step = d.steps[1]
    assert step.params["n_psf"] == 3
    # measured: 0.0878 -> 0.0486 (the automatic basis: 0.0248)
    assert step.error_after < 0.7 * step.error_before


def test_a_field_smoothed_too_much_is_relaxed(strong):
    image, truth = strong
    d = diagnose(image, psf_radius=truth.psf_radius, smoothing=10.0,
                 effects=["basis_size", "field_smoothing"])
    assert "field_smoothing" in d.added
    step = next(s for s in d.steps if s.effect == "field_smoothing")
    assert step.params["smoothing"] == pytest.approx(1.0)
    # measured: 0.0524 -> 0.0346
    assert step.error_after < 0.8 * step.error_before
