"""Honest residuals: a perfect model leaves only noise (chi2/dof ~ 1), a wrong one does not."""

import numpy as np
import pytest

from napari_psfspace import ProductConvolution, simulate_beads, simulate_psf
from napari_psfspace.core.beads.noise import NoiseModel, estimate_noise
from napari_psfspace.core.diagnosis.residuals import fit_beads


@pytest.fixture(scope="module")
def scene():
    image, truth = simulate_beads((512, 512), 40, aberrations="none", seed=0)
    r = truth.psf_radius
    size = 2 * int(np.ceil(1.2 * r)) + 1
    true_psf = truth.psf_at(256, 256, size)[None]
    op = ProductConvolution(true_psf, np.ones((1, 1, 1)), shape=image.shape,
                            grid=(np.array([0.0]), np.array([0.0])),
                            metadata={"psf_radius": r})
    camera = NoiseModel.from_camera(truth.gain, truth.offset, truth.read_noise)
    return image, truth, op, camera


def test_perfect_model_leaves_only_noise(scene):
    image, truth, op, camera = scene
    res = fit_beads(image, truth.positions, op, camera)
    s = res.summary()
    # measured: chi2/dof 0.987, error 0.00100 vs noise floor 0.00104
    assert s["chi2_dof"] == pytest.approx(1.0, abs=0.06)
    # the floor is what noise leaves after the same fit: each bead's error over its floor
    # averages 1 within 3 standard errors of the mean over the beads (measured 0.943,
    # SE 0.026; 1.00-1.05 on seeds 1-4). Counting every pixel's whole variance, as the
    # floor did, set it 5-10 % high and this mean 3.8 SE below 1.
    q = res.rel_energy / res.floor
    assert abs(q.mean() - 1.0) <= 3 * q.std(ddof=1) / np.sqrt(len(q))


def test_estimated_noise_model_gives_the_same_verdict(scene):
    image, truth, op, _ = scene
    s = fit_beads(image, truth.positions, op, estimate_noise(image)).summary()
    assert s["chi2_dof"] == pytest.approx(1.0, abs=0.08)  # measured 0.975


def test_wrong_model_is_caught(scene):
    _, _, op, camera = scene
    image, truth = simulate_beads((512, 512), 40, aberrations="moderate", seed=0)
    s = fit_beads(image, truth.positions, op, camera).summary()
    # measured: chi2/dof 15.2, error 0.020 against a floor of 0.0016
    assert s["chi2_dof"] > 5
    assert s["error"] > 5 * s["noise_floor"]


def test_amplitude_and_background_recovered(scene):
    image, truth, op, camera = scene
    res = fit_beads(image, truth.positions, op, camera, background="plane")
    expected_flux = truth.amplitudes * truth.gain  # ADU
    ratio = res.amplitude / expected_flux
    # the model is normalised over its patch, which holds this fraction of the energy
    inside = simulate_psf(None, optics=truth.optics, size=op.psf_size).sum()
    assert np.median(ratio) == pytest.approx(inside, rel=0.01)  # measured 0.937 vs 0.937
    iy, ix = np.round(truth.positions).astype(int).T
    true_bg = truth.background[iy, ix] * truth.gain + truth.offset
    assert np.median(np.abs(res.background - true_bg)) < 3.0  # ADU; measured ~1


def test_masked_pixels_are_ignored(scene):
    image, truth, op, camera = scene
    spoiled = image.astype(np.float64).copy()
    y, x = np.round(truth.positions[0]).astype(int)
    spoiled[y + 1, x] += 5000  # a hot pixel inside the first bead
    mask = np.zeros(image.shape, bool)
    mask[y + 1, x] = True
    hot = fit_beads(spoiled, truth.positions[:1], op, camera)
    masked = fit_beads(spoiled, truth.positions[:1], op, camera, pixel_mask=mask)
    assert hot.chi2[0] / hot.dof[0] > 20
    assert masked.chi2[0] / masked.dof[0] < 2
