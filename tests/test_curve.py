"""A family along one curve (core/family/curve): fields drawn from a known curve, learnt
back, and an image's field identified from five of its beads."""

import numpy as np
import pytest

from field_grid import GRID, N_I, SHAPE, nodes
from napari_psfspace.core.family.coordinates import bilinear, relative_field_error
from napari_psfspace.core.family.curve import (
    Curve,
    build_curve,
    identify_any,
    plane_design,
)
from napari_psfspace.core.family.dimensions import (
    Beads,
    build_model,
    choose_dimensions,
    choose_kind,
    clearly_lower,
)


def _coef(rng):
    """``C_0``, ``C_1``, ``C_2`` (3, G, I): smooth in the position, ``C_0`` with a strong
    first PSF coefficient (every PSF's norm well away from 0)."""
    u = nodes() / 255.0 - 0.5
    feats = np.column_stack([np.ones(len(u)), u, u ** 2])  # (G, 5)
    coef = np.einsum("gf,dfi->dgi", feats, rng.standard_normal((3, 5, N_I)))
    coef[0, :, 0] += 6.0
    coef[2] *= 0.5
    return coef


def _fields(coef, thetas):
    t = np.atleast_2d(thetas) @ plane_design(nodes(), SHAPE).T  # (K, G)
    return sum(t[..., None] ** d * coef[d][None] for d in range(3))


def _thetas(rng, k):
    return np.column_stack([rng.uniform(-1, 1, k), rng.uniform(-0.6, 0.6, (k, 2))])


def _beads(field, rng, n=5, sd=0.0, amplitude=None):
    centers = rng.uniform(20, 235, (n, 2))
    c = bilinear(GRID, centers) @ field
    g = np.ones(n) if amplitude is None else amplitude
    c = c * g[:, None] + sd * rng.standard_normal(c.shape)
    return c, np.full(n, sd if sd else 1e-9), centers


@pytest.fixture(scope="module")
def known():
    rng = np.random.default_rng(0)
    coef = _coef(rng)
    thetas = _thetas(rng, 10)
    return coef, thetas, _fields(coef, thetas)


def test_the_curve_learnt_from_noise_free_fields_holds_them(known):
    """Fields on a quadratic curve: the learnt curve (its own gauge of ``theta``) fits
    each of them, and the miss measured by leaving each out is that of a field the
    others' curve holds: both nil but for the learning's convergence (its squared
    residual falling by less than a millionth of itself; it reaches 1e-11)."""
    coef, thetas, fields = known
    curve = build_curve(fields, GRID, SHAPE, np.eye(N_I))
    spread = np.sqrt(((fields - fields.mean(axis=0)) ** 2).sum() / (fields ** 2).sum())
    for k, field in enumerate(fields):
        fit = curve.field(curve.eta(curve.thetas[k]))
        assert relative_field_error(fit, field) < 1e-6 * spread
    assert np.trace(curve.frame.miss_cov) < 1e-12 * np.mean((fields - fields.mean(0)) ** 2)


def test_the_linearised_model_is_the_curve_and_its_derivative(known):
    coef, thetas, fields = known
    curve = build_curve(fields, GRID, SHAPE, np.eye(N_I), miss=False)
    eta = np.array([0.3, -0.5, 0.8])
    lines = curve.linearized(eta)
    np.testing.assert_allclose(lines.field(eta), curve.field(eta), rtol=1e-12, atol=1e-12)
    h = 1e-5
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        numeric = (curve.field(eta + step) - curve.field(eta - step)) / (2 * h)
        # a quadratic in eta: the central difference is exact up to round-off
        np.testing.assert_allclose(lines.directions[j], numeric, rtol=1e-6, atol=1e-6)


def test_five_noise_free_beads_give_an_unseen_field(known):
    """A condition between those learnt: five noise-free beads of unequal amplitude give
    its field everywhere and the amplitudes, up to the prior's pull (the beads' noise
    over the prior's spread, squared: nil) and the Gauss-Newton's stop (a step below
    1e-8 of the prior's spread; it reaches 6e-7)."""
    coef, thetas, fields = known
    curve = build_curve(fields, GRID, SHAPE, np.eye(N_I), miss=False)
    rng = np.random.default_rng(1)
    truth = _fields(coef, np.array([0.2, -0.3, 0.25]))[0]
    g = np.array([0.8, 1.0, 1.3, 1.1, 0.9])
    c, sd, centers = _beads(truth, rng, amplitude=g)
    lines, (field, spread, fit) = identify_any(curve, c, sd, centers, krige=False)
    assert relative_field_error(field, truth) < 1e-5
    np.testing.assert_allclose(fit.amplitudes, g, rtol=1e-5)
    assert spread.shape == (len(nodes()),) and np.all(spread >= 0)


def test_the_choice_takes_the_curve_for_a_curved_family_and_lines_for_a_flat_one():
    """Twelve fields on a curve, beads of noise 0.01: the curve's three numbers identify
    a left-out image better than any number of lines; fields on three lines keep the
    lines (their curve's best fit misses them)."""
    rng = np.random.default_rng(2)
    coef = _coef(rng)
    thetas = _thetas(rng, 12)
    fields = _fields(coef, thetas)
    beads = [_as_beads(f, rng) for f in fields]
    out = choose_dimensions(fields, beads, GRID, SHAPE, np.eye(N_I))
    assert out["kind"] == "curve" and out["n_directions"] == 1
    assert len(out["curve"]["thetas"]) == 12
    lines = min(r["error"] for r in out["table"] if "curve" not in r)
    curved = [r["error"] for r in out["table"] if "curve" in r][0]
    assert curved < 0.5 * lines

    flat = build_model(fields[:4], 3, GRID, SHAPE, np.eye(N_I), miss=False)
    z = rng.standard_normal((12, 3)) * 2.0
    straight = np.array([flat.field(zk) for zk in z])
    out = choose_dimensions(straight, [_as_beads(f, rng) for f in straight], GRID, SHAPE,
                            np.eye(N_I))
    assert out["kind"] == "lines" and "curve" not in out


def _as_beads(field, rng):
    c, sd, centers = _beads(field, rng, n=30, sd=0.01)
    return Beads(centers, c, sd)


def _degree_choice(fields, rng):
    out = choose_dimensions(fields, [_as_beads(f, rng) for f in fields], GRID, SHAPE,
                            np.eye(N_I))
    row = [r for r in out["table"] if "curve" in r][0]
    return out, row["degree_errors"]


def test_a_cubic_replaces_the_quadratic_where_the_family_is_cubic():
    """Twelve fields on a cubic curve (``t`` up to 1.6, the cubic term a third of the
    quadratic's coefficients): the cubic identifies a left-out image from five beads
    better than the quadratic, which cannot hold the fields, and is kept."""
    rng = np.random.default_rng(5)
    coef = _coef(rng)
    coef = np.concatenate([coef, coef[2:] / 3.0 + 0.2 * coef[1:2]])
    t = _thetas(rng, 12) @ plane_design(nodes(), SHAPE).T  # (K, G)
    fields = sum(t[..., None] ** d * coef[d][None] for d in range(4))
    out, errors = _degree_choice(fields, rng)
    assert out["kind"] == "curve" and out["curve"]["degree"] == 3
    assert errors["3"] < 0.5 * errors["2"]


def test_the_quadratic_stays_where_a_cubic_only_fits_the_fields_noise():
    """Twelve fields on a quadratic curve, each with its own noise of a hundredth of
    their spread at every node: the cubic's fourth field follows that noise, so its
    left-out error is no lower by more than its standard error, and the quadratic
    stays."""
    rng = np.random.default_rng(6)
    fields = _fields(_coef(rng), _thetas(rng, 12))
    spread = float(np.std(fields - fields.mean(axis=0)))
    fields = fields + 0.01 * spread * rng.standard_normal(fields.shape)
    out, errors = _degree_choice(fields, rng)
    assert out["kind"] == "curve" and out["curve"]["degree"] == 2
    assert set(errors) == {"2", "3"}


def test_a_richer_model_is_kept_only_when_lower_beyond_the_draws_chance():
    """Paired errors whose differences have mean 0.01: kept where their standard
    deviation is 0.02 over 30 draws (standard error 0.0037), not where it is 0.1
    (0.018); never for a mean difference of 0 or below."""
    rng = np.random.default_rng(7)
    base = 1.0 + rng.uniform(0, 0.1, 30)
    noise = rng.standard_normal(30)
    noise = (noise - noise.mean()) / noise.std(ddof=1)  # mean 0, sd 1 exactly
    assert clearly_lower(base - 0.01 - 0.02 * noise, base)
    assert not clearly_lower(base - 0.01 - 0.1 * noise, base)
    assert not clearly_lower(base - 0.02 * noise, base)
    assert not clearly_lower(base + 0.01, base)


def test_the_lines_replace_the_curve_only_where_clearly_lower():
    """Paired left-out errors over 30 draws: lines lower on average but with the curve
    worse on one draw alone (a mean difference of 0.021 whose standard error is 0.023)
    keep the curve, as does a tie; lines lower on every draw replace it."""
    rng = np.random.default_rng(8)
    curve = 0.05 + rng.uniform(0, 0.02, 30)
    lines = curve + 0.002
    lines[7] = curve[7] - 0.7  # the curve's one bad draw
    assert lines.mean() < curve.mean()
    assert choose_kind(lines, curve) == "curve"
    assert choose_kind(curve, curve) == "curve"
    assert choose_kind(curve - 0.01, curve) == "lines"
    assert choose_kind(curve + 0.01, curve) == "curve"


def test_a_curve_is_a_model_identify_any_accepts():
    rng = np.random.default_rng(3)
    coef = _coef(rng)
    fields = _fields(coef, _thetas(rng, 8))
    curve = build_curve(fields, GRID, SHAPE, np.eye(N_I))
    assert isinstance(curve, Curve) and curve.degree == 2
    c, sd, centers = _beads(fields[3], rng, sd=0.01)
    lines, (field, spread, fit) = identify_any(curve, c, sd, centers)
    assert lines.n_directions == 3 and field.shape == fields[3].shape
    assert np.all(np.isfinite(field)) and np.all(np.isfinite(spread))


def test_each_bead_is_weighed_by_its_noise_and_the_family_miss(known):
    """A bead's whitener is the inverse square root of its noise's variance plus the
    family's miss there, spread over the coefficients and weighed by ``F``."""
    from dataclasses import replace

    coef, thetas, fields = known
    curve = build_curve(fields, GRID, SHAPE, np.eye(N_I), miss=False)
    cov = np.diag(np.arange(1.0, N_I + 1)) * 1e-4
    curve = replace(curve, frame=replace(curve.frame, miss_cov=cov), miss_factor=3.0)
    sd = np.array([0.01, 0.02])
    inv = curve.bead_whiteners(sd, np.array([[100.0, 100.0], [30.0, 200.0]]))
    expected = sd ** 2 + 3.0 * np.trace(cov) / N_I  # no miss scale: 1 everywhere
    for p in range(2):
        np.testing.assert_allclose(np.linalg.inv(inv[p].T @ inv[p]),
                                   expected[p] * np.eye(N_I), rtol=1e-12)
