"""Throughput over the field from bead amplitudes (core/photometry.py)."""

import numpy as np
import pytest

from napari_psfspace.core.diagnosis.photometry import (
    crossfit_log_residuals,
    fit_throughput,
    throughput_at,
    throughput_map,
    trend_p_value,
)


def _beads(n=200, seed=0, spread=0.1):
    rng = np.random.default_rng(seed)
    shape = (500, 700)
    pos = rng.uniform((0, 0), (shape[0] - 1, shape[1] - 1), size=(n, 2))
    true = np.array([0.2, 0.1, -0.05, -0.4, 0.05, -0.3])  # 1; u, v; u^2, uv, v^2
    amp = throughput_at(true, pos, shape) * np.exp(rng.normal(0, spread, n))
    return pos, amp, shape, true


def test_fit_recovers_a_log_quadratic_field():
    pos, amp, shape, true = _beads(spread=0.05)
    coef = fit_throughput(pos, amp, shape, degree=2, radial=False)
    # 200 beads with 5 % scatter: each coefficient within 0.03 (measured <= 0.012)
    assert np.abs(coef - true).max() < 0.03


def test_radial_fit_recovers_an_off_centre_paraboloid():
    rng = np.random.default_rng(3)
    shape = (500, 700)
    pos = rng.uniform((0, 0), (shape[0] - 1, shape[1] - 1), size=(300, 2))
    true = np.array([0.1, 0.08, -0.06, -0.3, 0.0, -0.3])  # centre off the field's
    amp = throughput_at(true, pos, shape) * np.exp(rng.normal(0, 0.05, 300))
    coef = fit_throughput(pos, amp, shape)  # radial by default
    assert coef[4] == 0.0 and coef[3] == coef[5]
    assert np.abs(coef - true).max() < 0.02
    # a saddle is no paraboloid of revolution: the radial fit leaves it in the residual
    saddle = throughput_at([0, 0, 0, 0.4, 0, -0.4], pos, shape)
    flat = fit_throughput(pos, saddle, shape)
    assert np.abs(flat[3]) < 0.05  # measured 0.028 (the saddle's 0.4 projects a little)


def test_map_is_normalised_to_a_field_mean_of_one():
    pos, amp, shape, _ = _beads()
    coef = fit_throughput(pos, amp, shape)
    full = throughput_map(coef, np.arange(shape[0]), np.arange(shape[1]), shape)
    assert abs(full.mean() - 1.0) < 0.01
    raw = throughput_map(coef, [0.0], [0.0], shape, normalise=False)
    assert raw[0, 0] == pytest.approx(throughput_at(coef, [[0.0, 0.0]], shape)[0])


def test_held_out_error_drops_with_the_right_model_only():
    pos, amp, shape, _ = _beads(spread=0.1)
    fold = np.arange(len(amp)) % 5
    flat = np.nanmean(crossfit_log_residuals(pos, amp, fold, shape, degree=0) ** 2)
    quad = np.nanmean(crossfit_log_residuals(pos, amp, fold, shape, degree=2) ** 2)
    # the held-out error reaches the beads' own scatter (0.1^2) within 30 %
    assert quad < 1.3 * 0.1**2 < flat
    # on beads of uniform throughput the quadratic model cannot do better than a constant
    rng = np.random.default_rng(3)
    same = np.exp(rng.normal(0, 0.1, len(amp)))
    flat = np.nanmean(crossfit_log_residuals(pos, same, fold, shape, degree=0) ** 2)
    quad = np.nanmean(crossfit_log_residuals(pos, same, fold, shape, degree=2) ** 2)
    assert quad > 0.95 * flat


def test_bad_amplitudes_and_too_few_beads():
    pos, amp, shape, _ = _beads(n=20)
    with pytest.raises(ValueError, match="amplitude"):
        fit_throughput(pos, -amp, shape)
    with pytest.raises(ValueError, match="Too few beads"):
        fit_throughput(pos[:6], amp[:6], shape, degree=2, radial=False)
    with pytest.raises(ValueError, match="Too few beads"):  # radial: 4 + 2 needed
        fit_throughput(pos[:5], amp[:5], shape, degree=2)


def test_trend_test_holds_its_level_with_doublets_and_sees_a_vignetting():
    shape = (1024, 1024)
    rng = np.random.default_rng(11)
    # the null: no trend; lognormal brightness plus 5 % doublets (twice as bright),
    # a heavy upper tail the F-test's Gaussian theory does not assume
    p_null = []
    for _ in range(200):
        pos = rng.uniform(0, 1023, size=(60, 2))
        amp = np.exp(rng.normal(0, 0.25, 60)) * np.where(rng.random(60) < 0.05, 2.0, 1.0)
        p_null.append(trend_p_value(pos, amp, shape, n_perm=400, seed=1)["p"])
    # the permutation p is uniform under the null: 5 % rejected at 0.05 (measured 4.0 %)
    assert 0.02 < np.mean(np.array(p_null) <= 0.05) < 0.09
    # 150 beads of spread 0.25 with a centred 40 % fall-off to the corners: p below the
    # diagnosis' 0.005 (measured 0.0002 = 1 / 4001), and the held-out test much weaker
    pos = rng.uniform(0, 1023, size=(150, 2))
    rho2 = ((pos - 511.5) ** 2).sum(axis=1) / (2 * 511.5**2)
    amp = (1 - 0.4 * rho2) * np.exp(rng.normal(0, 0.25, 150))
    out = trend_p_value(pos, amp, shape)
    assert out["p"] < 0.005 and out["p_f"] < 0.005
    assert out["n_beads"] == 150
    with pytest.raises(ValueError, match="degree1"):
        trend_p_value(pos, amp, shape, degree0=2, degree1=2)
