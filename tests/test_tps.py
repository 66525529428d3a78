"""Tests of the smoothing thin-plate spline (core/tps.py, paper Appendix C, eq. 8)."""

import numpy as np
import pytest

from napari_psfspace.core.model.tps import ThinPlateSpline

M = 60
NOISE = 0.05


def _f(p):
    return np.sin(p[:, 0] / 30.0) * np.cos(p[:, 1] / 25.0)


def _data(seed, m=M, noise=NOISE):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, 100, (m, 2))
    return pts, _f(pts) + noise * rng.standard_normal(m), rng


def _weighted_loo_score(spline, weights):
    """The selection score (weights normalised to mean 1) from the closed-form LOO."""
    w = weights / weights.mean()
    return float((w * spline.loo_residuals**2).sum() / len(w))


def test_interpolates_without_smoothing():
    pts, y, rng = _data(0)
    w = rng.uniform(0.5, 2.0, M)
    for weights in (None, w):
        sp = ThinPlateSpline(pts, y, weights=weights, smoothing=0.0)
        # measured 2.3e-14 on seed 0
        assert np.abs(sp(pts) - y).max() < 1e-8
        assert sp.effective_dof[0] == M
        assert np.all(sp.loo_residuals == 0)  # documented: zero where it interpolates


@pytest.mark.parametrize("eta", [0.0, 1e-4, 1e-1, 10.0, 1e4])
def test_affine_reproduced_for_any_smoothing(eta):
    pts, _, rng = _data(1)
    affine = lambda p: 0.7 - 0.02 * p[:, 0] + 0.05 * p[:, 1]  # noqa: E731
    sp = ThinPlateSpline(pts, affine(pts), smoothing=eta)
    test = rng.uniform(-20, 120, (200, 2))  # includes extrapolation
    # affine functions are in the null space of the penalty: measured 4e-15
    assert np.abs(sp(test) - affine(test)).max() < 1e-8


def test_large_smoothing_gives_affine_fit():
    pts, y, _ = _data(2)
    sp = ThinPlateSpline(pts, y, smoothing=1e12)
    a = np.column_stack([np.ones(M), pts])
    coef = np.linalg.lstsq(a, y, rcond=None)[0]
    # measured 2e-12 difference from least squares; dof -> 3
    assert np.abs(sp(pts) - a @ coef).max() < 1e-6
    assert abs(sp.effective_dof[0] - 3) < 1e-6


def test_recovers_smooth_function_below_noise():
    pts, y, _ = _data(3, m=200)
    sp = ThinPlateSpline(pts, y)
    g = np.stack(np.meshgrid(np.linspace(5, 95, 50), np.linspace(5, 95, 50),
                             indexing="ij"), -1).reshape(-1, 2)
    rms = float(np.sqrt(np.mean((sp(g) - _f(g)) ** 2)))
    # measured rms 0.0227 (67 dof) on seed 3, noise 0.05
    assert rms < 0.7 * NOISE
    assert 3 < sp.effective_dof[0] < 200
    assert np.isfinite(sp.score[0])


def _brute_loo(pts, y, weights, eta, scale, *, compensate=True, fixed_scale=True):
    out = np.empty(len(pts))
    for m in range(len(pts)):
        keep = np.arange(len(pts)) != m
        w = None if weights is None else weights[keep]
        e = eta
        if compensate and weights is not None:
            # the spline divides its weights by their mean: refitting on M - 1 points
            # with the same eta would change the balance between fit and penalty
            e = eta * weights.mean() / weights[keep].mean()
        sp = ThinPlateSpline(pts[keep], y[keep], weights=w, smoothing=e,
                             scale=scale if fixed_scale else None)
        out[m] = y[m] - sp(pts[m:m + 1])[0]
    return out


@pytest.mark.parametrize("eta", [1e-3, 1e-1])
@pytest.mark.parametrize("weighted", [False, True])
def test_loo_residuals_equal_brute_force(eta, weighted):
    pts, y, rng = _data(4)
    w = rng.uniform(0.5, 2.0, M) if weighted else None
    sp = ThinPlateSpline(pts, y, weights=w, smoothing=eta)
    brute = _brute_loo(pts, y, w, eta, sp._scale)
    # measured max relative difference 1e-13 (eta 1e-3) and 4e-15 (eta 0.1) on seed 4
    assert np.abs(sp.loo_residuals - brute).max() < 1e-8 * np.abs(brute).max()


@pytest.mark.parametrize("weighted", [False, True])
def test_standardized_residuals_sit_between_the_residual_and_the_loo_one(weighted):
    pts, y, rng = _data(4)
    w = rng.uniform(0.5, 2.0, M) if weighted else None
    sp = ThinPlateSpline(pts, y, weights=w, smoothing=1e-2)
    r, loo, z = sp.residuals[:, 0], sp.loo_residuals, sp.standardized_residuals
    # r / sqrt(1 - S) is the geometric mean of r and r / (1 - S): z^2 = r * loo
    np.testing.assert_allclose(z ** 2, r * loo, rtol=1e-12, atol=0)
    assert np.all(np.sign(z) == np.sign(r))
    assert np.all(np.abs(r) <= np.abs(z)) and np.all(np.abs(z) <= np.abs(loo))
    # an interpolating spline leaves none
    sp0 = ThinPlateSpline(pts, y, smoothing=0.0)
    assert np.all(sp0.standardized_residuals == 0)


def test_vector_values_get_their_own_smoothing():
    pts, y, rng = _data(6)
    noisy = _f(pts) + 0.5 * rng.standard_normal(M)  # much noisier column
    sp = ThinPlateSpline(pts, np.column_stack([y, noisy]))
    assert sp(pts[:3]).shape == (3, 2)
    assert sp.loo_residuals.shape == (M, 2)
    # the noisier column is smoothed more: measured eta 0.017 vs 0.30 (ratio 18),
    # dof 36 vs 14.5
    assert sp.smoothing[1] > 5 * sp.smoothing[0]
    assert sp.effective_dof[1] < sp.effective_dof[0]
    # each column equals its scalar fit with the same eta
    for j, col in enumerate((y, noisy)):
        single = ThinPlateSpline(pts, col, smoothing=sp.smoothing[j])
        assert np.abs(single(pts) - sp(pts)[:, j]).max() < 1e-10  # measured 1e-15


def test_weights_pull_the_fit():
    pts, y, _ = _data(7)
    w = np.ones(M)
    w[0] = 1e4
    heavy = ThinPlateSpline(pts, y, weights=w, smoothing=1.0)
    plain = ThinPlateSpline(pts, y, smoothing=1.0)
    # measured: residual at the heavy point 130x smaller (ratio 0.0078)
    assert abs(heavy.residuals[0, 0]) < 0.1 * abs(plain.residuals[0, 0])
    # weights are relative: scaling all of them changes nothing
    scaled = ThinPlateSpline(pts, y, weights=7.0 * w, smoothing=1.0)
    assert np.abs(scaled(pts) - heavy(pts)).max() < 1e-10


def test_collinear_points_raise():
    pts = np.column_stack([np.linspace(0, 10, 8), 2 * np.linspace(0, 10, 8) + 1])
    with pytest.raises(ValueError, match="collinear"):
        ThinPlateSpline(pts, np.arange(8.0))


def test_fewer_than_four_points_raise():
    with pytest.raises(ValueError, match="at least 4 points, got 3"):
        ThinPlateSpline([[0, 0], [1, 0], [0, 1]], [1.0, 2.0, 3.0])


def test_invalid_arguments_raise():
    pts, y, _ = _data(8, m=10)
    with pytest.raises(ValueError, match="`weights`"):
        ThinPlateSpline(pts, y, weights=np.r_[0.0, np.ones(9)])
    with pytest.raises(ValueError, match="`weights`"):
        ThinPlateSpline(pts, y, weights=np.ones(5))
    with pytest.raises(ValueError, match="`smoothing`"):
        ThinPlateSpline(pts, y, smoothing=-1.0)
    bad = y.copy()
    bad[2] = np.nan
    with pytest.raises(ValueError, match="`values`"):
        ThinPlateSpline(pts, bad)


def test_many_samples_are_binned_without_losing_accuracy():
    """Above max_nodes the spline fits weighted cell means. Measured (2500 samples, noise
    0.05): exact 6.6 s, rms vs truth 0.0076; binned to 882 nodes 0.76 s, 0.0077; LOO
    residuals correlate 1.000 with the exact ones."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, [600, 900], (1500, 2))

    def f(p):
        return np.sin(p[:, 0] / 150) + np.cos(p[:, 1] / 200)

    y = f(pts) + 0.05 * rng.standard_normal(len(pts))
    exact = ThinPlateSpline(pts, y, max_nodes=None)
    binned = ThinPlateSpline(pts, y, max_nodes=400)
    assert binned.n_nodes <= 400 and exact.n_nodes == 1500
    grid = rng.uniform(0, [600, 900], (2000, 2))
    rms_exact = np.sqrt(np.mean((exact(grid) - f(grid)) ** 2))
    rms_binned = np.sqrt(np.mean((binned(grid) - f(grid)) ** 2))
    assert rms_binned < 1.3 * rms_exact + 1e-3
    assert binned.loo_residuals.shape == (1500,)
    assert np.corrcoef(binned.loo_residuals, exact.loo_residuals)[0, 1] > 0.98


@pytest.mark.parametrize("max_nodes", [None, 40])
def test_refit_equals_a_fresh_fit(max_nodes):
    """``refit`` reuses the factorisation: the same spline as a new fit of the values, to
    float64 rounding (eta chosen the same way), binned or not; bad values are refused."""
    pts, y, rng = _data(3, m=90)
    w = rng.uniform(0.5, 2.0, len(pts))
    first = ThinPlateSpline(pts, y, weights=w, max_nodes=max_nodes)
    z = np.column_stack([_f(pts[:, ::-1]), y ** 2]) + 0.02 * rng.standard_normal((90, 2))
    fresh = ThinPlateSpline(pts, z, weights=w, max_nodes=max_nodes)
    again = first.refit(z)
    assert np.array_equal(again.smoothing, fresh.smoothing)
    grid = rng.uniform(0, 100, (200, 2))
    scale = np.abs(z).max()
    assert np.allclose(again(grid), fresh(grid), rtol=0, atol=1e-10 * scale)
    assert np.allclose(again.loo_residuals, fresh.loo_residuals, rtol=0, atol=1e-10 * scale)
    assert np.allclose(first(grid), ThinPlateSpline(pts, y, weights=w,
                                                    max_nodes=max_nodes)(grid))
    assert again(grid).shape == (200, 2) and first(grid).shape == (200,)
    with pytest.raises(ValueError, match="90 rows"):
        first.refit(z[:10])
    with pytest.raises(ValueError, match="NaN"):
        first.refit(np.full(90, np.nan))


@pytest.mark.parametrize("block", [None, 5])
def test_the_chosen_smoothing_is_the_least_loo_score_of_the_grid(block, monkeypatch):
    """The selection scores the grid of smoothing values a block at a time: each column's
    chosen value has the least weighted leave-one-out score of the 97 values (every
    value's score the closed-form LOO of a fit at that smoothing), and its score is that
    fit's. The same with blocks of 5 values as with the whole grid in one product."""
    import napari_psfspace.core.model.tps as tps

    pts, y, rng = _data(7)
    vals = np.column_stack([y, _f(pts[:, ::-1]) + NOISE * rng.standard_normal(M)])
    w = rng.uniform(0.5, 2.0, M)
    if block is not None:
        monkeypatch.setattr(tps, "SELECT_BLOCK", M * vals.shape[1] * block)
    sp = ThinPlateSpline(pts, vals, weights=w, max_dof=None)
    lam = sp._factors[6]
    grid = max(float(lam.max()), 1e-12) * np.logspace(-9, 3, 97)
    for j in range(vals.shape[1]):
        scores = np.array([_weighted_loo_score(
            ThinPlateSpline(pts, vals[:, j], weights=w, smoothing=e), w) for e in grid])
        best = int(np.argmin(scores))
        assert sp.smoothing[j] == grid[best]
        # the same arithmetic up to the order of its sums: rounding, relative
        assert abs(sp.score[j] - scores[best]) <= 1e-9 * scores[best]


def test_the_spline_is_scipys_thin_plate_rbf():
    """The spline kept here (its eigendecomposition gives every smoothing value's
    leave-one-out error at once) is the function scipy's ``RBFInterpolator`` fits with
    the same kernel, degree-1 polynomial and smoothing ``eta / w_m`` per sample, in the
    spline's scaled coordinates: the two solve one linear system, so they agree to
    rounding (1e-9 of the values' scale), with a given smoothing and with the
    leave-one-out choice."""
    from scipy.interpolate import RBFInterpolator

    rng = np.random.default_rng(11)
    pts = rng.uniform(0, 500, (60, 2))
    vals = np.column_stack([np.sin(pts[:, 0] / 90.0) + 0.05 * rng.normal(size=60),
                            np.cos(pts[:, 1] / 70.0) * pts[:, 0] / 500.0,
                            rng.normal(size=60)])
    w = rng.uniform(0.5, 2.0, 60)
    new = rng.uniform(0, 500, (200, 2))
    for smoothing in (0.01, None):
        tps = ThinPlateSpline(pts, vals, weights=w, smoothing=smoothing)
        z = (pts - tps._center) / tps._scale
        zn = (new - tps._center) / tps._scale
        wn = w / w.mean()
        for j, eta in enumerate(tps.smoothing):
            ref = RBFInterpolator(z, vals[:, j], kernel="thin_plate_spline", degree=1,
                                  smoothing=eta / wn)(zn)
            np.testing.assert_allclose(tps(new)[:, j], ref, rtol=0, atol=1e-9)
