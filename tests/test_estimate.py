"""End-to-end estimation on the simulator, and every bad input the brief lists.

Accuracy bounds are those of the issue (mean <= 0.05 for moderate aberrations, <= 0.12 for
strong ones, at most a third of the best shift-invariant PSF's error), asserted on small
seeded fields; bench/bench_accuracy.py prints the full table on the sizes the issue names.
"""

import numpy as np
import pytest

import napari_psfspace as ps
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.model.estimate import iter_estimate
from napari_psfspace.core.simulation.metrics import evaluate_against_truth, psf_error


@pytest.fixture(scope="module")
def moderate():
    image, truth = ps.simulate_beads((768, 768), 90, aberrations="moderate", seed=0)
    est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius))
    return image, truth, est


def test_accuracy_moderate(moderate):
    _, truth, est = moderate
    r = evaluate_against_truth(est.operator, truth, 8)
    # measured (seed 0): aligned mean 0.040, unaligned 0.053, shift-invariant 0.128
    assert r["aligned"]["mean"] <= 0.05
    assert r["ratio"] <= 1 / 3
    assert r["aligned"]["mean"] < r["unaligned"]["mean"]  # alignment can only help
    assert r["edges"]["mean"] <= 0.075  # measured 0.057: grid reaching the border


def test_accuracy_strong():
    image, truth = ps.simulate_beads((1024, 1024), 140, aberrations="strong", seed=1)
    op = ps.estimate_operator(image, psf_radius=truth.psf_radius, holdout=None)
    r = evaluate_against_truth(op, truth, 8)
    # measured: aligned mean 0.071, shift-invariant 0.238, ratio 0.30
    assert r["aligned"]["mean"] <= 0.12
    assert r["ratio"] <= 1 / 3


def test_aberration_free_field_is_nearly_shift_invariant():
    image, truth = ps.simulate_beads((512, 512), 40, aberrations="none", seed=0)
    op = ps.estimate_operator(image, psf_radius=truth.psf_radius)
    r = evaluate_against_truth(op, truth, 6)
    assert r["aligned"]["mean"] <= 0.03  # measured 0.0205 (window truncation 0.012 + noise)
    assert op.n_psf <= 3  # measured 1-2: nothing varies, the held-out rule keeps it small
    corner, centre = op.psf_at(40, 40), op.psf_at(256, 256)
    assert psf_error(corner, centre, align=False) <= 0.02


def test_estimation_records(moderate):
    image, truth, est = moderate
    op, meta = est.operator, est.operator.metadata
    assert op.image_shape == image.shape
    assert op.psf_size == 2 * int(np.ceil(1.2 * truth.psf_radius)) + 1
    # no cap but the beads' support: half the inliers (pca.learn_basis)
    assert meta["n_psf"] == op.n_psf and 1 <= op.n_psf <= (meta["n_beads_used"] - 2) // 2
    fc = meta["field_constraint"]
    assert fc["chosen"] in ("where-needed", "cone")
    assert fc[fc["chosen"]] <= fc["cone"] * (1 + 1e-9)  # never worse than the paper's
    assert len(meta["smoothing"]) == op.n_psf
    assert meta["heldout"]["n_beads"] >= 10
    # the held-out residual can't beat the noise floor, and stays within 2x of it here
    h = meta["heldout"]
    assert h["noise_floor_mean"] < h["residual_mean"] < 2 * h["noise_floor_mean"] + 0.02
    counts = est.beads.counts()
    assert counts["kept"] + counts["outlier"] == len(est.patches)
    assert counts["kept"] >= 0.85 * len(truth.positions)  # measured 79/90 kept (6 border)


def test_psf_at_beads_matches_their_patches(moderate):
    """The operator reproduces each bead it was fitted on, to the noise level."""
    _, _, est = moderate
    inl = est.basis.inliers
    errs = [psf_error(est.operator.psf_at(*c), p, align=False)
            for c, p in zip(est.patches.centers[inl], est.patches.psf[inl], strict=True)]
    h = est.operator.metadata["heldout"]
    # measured: median 0.055 vs. a held-out noise floor (median) of 0.047
    assert np.median(errs) <= h["noise_floor_median"] * 1.5 + 0.01


def test_psf_at_beads_matches_fitted_coefficients():
    """With interpolating splines (eta = 0) and a fine grid, the map at each bead equals
    that bead's own coefficients (when they lie in the cone)."""
    image, truth = ps.simulate_beads((512, 512), 40, aberrations="moderate", seed=3)
    est = run_with_progress(iter_estimate(image, psf_radius=truth.psf_radius, n_psf=3,
                                          smoothing=0.0, grid_step=1.0, holdout=None))
    op, basis = est.operator, est.basis
    centers = est.patches.centers[basis.inliers]
    fitted = op.coefficients_at(centers[:, 0], centers[:, 1])
    beta = basis.coefficients / (basis.coefficients @ op.basis.sum(axis=(1, 2)))[:, None]
    angle = est.cone.angle(basis.coefficients)
    inside = angle < 1e-6
    assert inside.sum() >= len(inside) // 2
    rel = np.linalg.norm(fitted - beta, axis=1) / np.linalg.norm(beta, axis=1)
    assert np.max(rel[inside]) < 3e-3  # measured 6.4e-4 (bilinear between 1-px nodes)


def test_progress_is_reported_and_monotone():
    image, truth = ps.simulate_beads((384, 384), 25, aberrations="moderate", seed=2)
    seen = []
    ps.estimate_operator(image, psf_radius=truth.psf_radius, progress=seen.append)
    fractions = [p.fraction for p in seen]
    assert [p.stage for p in seen][:3] == ["detect", "centre", "patches"]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.float32, np.float64])
def test_any_real_dtype(dtype):
    image, truth = ps.simulate_beads((384, 384), 25, aberrations="moderate", seed=4,
                                     amplitude=(2e3, 4e3), offset=10.0)
    if dtype == np.uint8:
        image = np.clip(image // 4, 0, 254)  # keep below saturation
    op = ps.estimate_operator(image.astype(dtype), psf_radius=truth.psf_radius, n_psf=2,
                              holdout=None)
    assert np.isfinite(op.coefficients).all()
    assert abs(op.psf_at(192, 192).sum() - 1) < 1e-9


# ---------------------------------------------------------------- bad input -------------

def _noise(shape=(256, 256), seed=0):
    return np.random.default_rng(seed).normal(100, 5, shape).astype(np.float32)


def test_no_beads():
    with pytest.raises(ps.NoBeadsError, match="No beads found.*`threshold`"):
        ps.estimate_operator(_noise(), psf_radius=6)


def test_constant_image():
    with pytest.raises(ps.NoBeadsError, match="constant"):
        ps.estimate_operator(np.full((200, 200), 7, np.uint16), psf_radius=6)


def test_too_few_beads_for_the_basis_size():
    image, truth = ps.simulate_beads((256, 256), 4, aberrations="moderate", seed=0)
    with pytest.raises(ps.NoBeadsError, match=r"Too few usable beads.*`n_psf` = 5"):
        ps.estimate_operator(image, psf_radius=truth.psf_radius, n_psf=5)


def test_nans():
    image = _noise()
    image[10, 20] = np.nan
    with pytest.raises(ValueError, match="`image` contains 1 NaN"):
        ps.estimate_operator(image, psf_radius=6)


@pytest.mark.parametrize("shape", [(50,), (3, 64, 64), (2, 3, 64, 64)])
def test_wrong_dimensions(shape):
    msg = "Pass one slice.*estimate_operator_3d" if len(shape) == 3 else "2-D image"
    with pytest.raises(ValueError, match=msg):
        ps.estimate_operator(np.zeros(shape, np.float32), psf_radius=4)


def test_stack_error_names_the_sharpest_slice():
    image, truth = ps.simulate_beads((128, 128), 5, aberrations="none", seed=0)
    stack = np.stack([np.full_like(image, 100), image, np.full_like(image, 100)])
    with pytest.raises(ValueError, match=r"e\.g\. `image\[1\]`"):
        ps.estimate_operator(stack, psf_radius=truth.psf_radius)


def test_all_beads_at_the_border():
    image = np.full((200, 200), 100.0, np.float32)
    yy, xx = np.mgrid[:200, :200]
    for y, x in [(3, 100), (196, 50), (100, 2), (60, 197), (4, 4)]:
        image += 5000 * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * 1.5**2))
    image += np.random.default_rng(0).normal(0, 3, image.shape).astype(np.float32)
    with pytest.raises(ps.NoBeadsError, match=r"0 kept.*5 border"):
        ps.estimate_operator(image, psf_radius=6)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"psf_radius": -1}, "`psf_radius`"),
    ({"psf_radius": 1000}, "`psf_radius`.*too large"),
    ({"psf_radius": 5, "n_psf": 0}, "`n_psf`"),
    ({"psf_radius": 5, "n_psf": "many"}, "`n_psf`"),
    ({"psf_radius": 5, "smoothing": -1.0}, "`smoothing`"),
    ({"psf_radius": 5, "threshold": 0}, "`threshold`"),
    ({"psf_radius": 5, "holdout": 0.9}, "`holdout`"),
])
def test_bad_parameters(kwargs, match):
    image, _ = ps.simulate_beads((256, 256), 12, aberrations="none", seed=0)
    with pytest.raises(ValueError, match=match):
        ps.estimate_operator(image, **kwargs)


def test_saturated_beads_are_not_used():
    image, truth = ps.simulate_beads((384, 384), 25, aberrations="none", seed=5,
                                     amplitude=(2e5, 3e6), gain=2.0)
    assert (image == 65535).any()
    beads = ps.detect_beads(image, truth.psf_radius)
    assert beads.counts()["saturated"] >= 1
