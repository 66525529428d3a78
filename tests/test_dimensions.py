"""A family's few dimensions (core/family/dimensions, coordinates) and the clicked-bead
check (core/restore/bead_check), on fields and beads drawn from known models."""

import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve

from field_grid import GRID, N_I, SHAPE
from field_grid import nodes as _nodes
from napari_psfspace.core.family.coordinates import (
    CoordinateFit,
    Model,
    design,
    fit_coordinates,
    krige_miss,
    relative_field_error,
    relative_field_errors,
    solve_coordinates,
    solve_nested,
    whitened,
)
from napari_psfspace.core.family.dimensions import (
    Beads,
    build_model,
    choose_dimensions,
    misses,
    noise_factor,
    principal,
)
from napari_psfspace.core.restore.bead_check import OUTLIER, check_beads


def _smooth_fields(rng, n, scale=1.0):
    """``n`` smooth fields (n, G, I): low-order polynomials of the position."""
    u = _nodes() / 255.0 - 0.5
    feats = np.column_stack([np.ones(len(u)), u, u ** 2, u[:, :1] * u[:, 1:]])  # (G, 6)
    return scale * np.einsum("gf,nfi->ngi", feats, rng.standard_normal((n, feats.shape[1], N_I)))


def _model(rng, n_l=3, miss=0.0, length=60.0):
    mean = _smooth_fields(rng, 1)[0] + np.r_[4.0, np.zeros(N_I - 1)]  # a strong first PSF
    dirs = _smooth_fields(rng, n_l)
    flat = np.linalg.qr(dirs.reshape(n_l, -1).T)[0].T  # orthonormal directions
    cov = miss ** 2 * np.eye(N_I)
    return Model(GRID, SHAPE, mean, flat.reshape(n_l, *mean.shape),
                 np.array([4.0, 1.0, 0.25])[:n_l], cov, length, np.eye(N_I))


def _beads(model, z, rng, n=5, sd=0.0, amplitude=None):
    centers = rng.uniform(20, 235, (n, 2))
    from napari_psfspace.core.family.coordinates import bilinear

    c = bilinear(model.grid, centers) @ model.field(z)
    g = np.ones(n) if amplitude is None else amplitude
    c = c * g[:, None] + sd * rng.standard_normal(c.shape)
    return c, np.full(n, sd if sd else 1e-9), centers


def test_noise_free_beads_give_the_coordinates_and_amplitudes_exactly():
    rng = np.random.default_rng(0)
    model = _model(rng)
    z = np.array([1.5, -0.7, 0.3])
    g = np.array([0.8, 1.0, 1.3, 1.1, 0.9])
    c, sd, centers = _beads(model, z, rng, amplitude=g)
    fit = fit_coordinates(model, c, sd, centers, n_iter=200)
    # the prior's pull is (sd / coordinate sd)^2 ~ 1e-18 of the data's: float64 round-off
    np.testing.assert_allclose(fit.z, z, atol=1e-6)
    np.testing.assert_allclose(fit.amplitudes, g, rtol=1e-6)
    assert np.abs(fit.residuals).max() < 1e-6


def test_the_posterior_covariance_is_the_spread_of_the_fits():
    """200 noisy draws of the same beads: the fits scatter about the truth as their
    posterior covariance says (each coordinate's squared standardized error averages 1;
    its mean over 200 draws lies within 1 +- 0.3, 3 sd of a chi^2_200 / 200)."""
    rng = np.random.default_rng(1)
    model = _model(rng)
    z = np.array([0.5, 0.2, -0.4])
    c0, _, centers = _beads(model, z, rng)
    sd = 0.02
    errs, covs = [], []
    for _ in range(200):
        c = c0 + sd * rng.standard_normal(c0.shape)
        fit = fit_coordinates(model, c, np.full(5, sd), centers, amplitude_range=(1.0, 1.0))
        errs.append(fit.z - z)
        covs.append(fit.cov)
    chi = [e @ np.linalg.solve(cv, e) / 3 for e, cv in zip(errs, covs, strict=True)]
    assert 0.7 < np.mean(chi) < 1.3


def test_kriging_of_the_miss_against_the_dense_formula():
    """The separable shortcut of the variance (one P x P matrix) equals the posterior
    variance computed from the dense covariances; the mean interpolates the residual of a
    noise-free bead at its own position."""
    from dataclasses import replace

    from napari_psfspace.core.family.coordinates import bilinear

    rng = np.random.default_rng(2)
    model = _model(rng, miss=0.3, length=50.0)
    nodes = _nodes()
    scale = 0.5 + ((nodes - 128.0) ** 2).sum(axis=1) / 128.0 ** 2  # larger at the rim
    model = replace(model, miss_scale=scale)
    centers = rng.uniform(20, 235, (4, 2))
    res = 0.3 * rng.standard_normal((4, N_I))
    noise = np.array([0.05, 0.1, 0.02, 0.07])
    fit = CoordinateFit(np.zeros(3), np.zeros((3, 3)), np.ones(4), np.zeros((4, N_I)), res,
                        noise, centers)
    pts = rng.uniform(0, 255, (7, 2))
    mean, var = krige_miss(model, fit, pts)

    def sc(a):
        return bilinear(GRID, a) @ scale

    def k(a, b):
        d2 = ((a[:, None] - b[None]) ** 2).sum(-1)
        return np.exp(-0.5 * d2 / 50.0 ** 2) * np.outer(sc(a), sc(b))

    s = np.kron(k(centers, centers), model.miss_cov) + np.kron(np.diag(noise ** 2),
                                                               np.eye(N_I))
    cross = np.kron(k(pts, centers), model.miss_cov)  # (Q I, P I)
    f = cho_factor(s)
    dense_mean = (cross @ cho_solve(f, res.ravel())).reshape(7, N_I)
    dense_var = [np.trace(sc(pts[q:q + 1])[0] ** 2 * model.miss_cov
                          - cross[q * N_I:(q + 1) * N_I] @ cho_solve(
                              f, cross[q * N_I:(q + 1) * N_I].T)) for q in range(7)]
    np.testing.assert_allclose(mean, dense_mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(var, dense_var, rtol=1e-9, atol=1e-12)
    # a noise-free bead: the kriged miss at it is its residual
    exact = CoordinateFit(np.zeros(3), np.zeros((3, 3)), np.ones(4), np.zeros((4, N_I)),
                          res, np.full(4, 1e-9), centers)
    at, var_at = krige_miss(model, exact, centers)
    np.testing.assert_allclose(at, res, atol=1e-6)
    assert var_at.max() < 1e-6 * np.trace(model.miss_cov)


def test_the_miss_scale_follows_residuals_that_grow_to_the_rim():
    """Residual fields whose power grows as exp(0.8 r^2) to the rim (r: distance from
    the centre, -1 to 1 per axis): the scale's log is a quadratic of the position, so the
    fit gives it back exactly up to the mean's normalisation; the residuals' shape over
    the field (a smooth random field) does not enter."""
    from napari_psfspace.core.family.miss import miss_model

    rng = np.random.default_rng(11)
    nodes = _nodes()
    u = nodes / 127.5 - 1.0
    true = np.exp(0.4 * (u ** 2).sum(axis=1))  # standard deviation
    # many fields: the mean squared residual at each node is its expectation to 1 %
    res = rng.standard_normal((4000, len(nodes), N_I)) * true[None, :, None]
    cov, length, scale = miss_model(res, nodes)
    want = true / np.sqrt(np.mean(true ** 2))
    np.testing.assert_allclose(scale, want, rtol=0.02)
    assert np.mean(scale ** 2) == pytest.approx(1.0)


def test_the_choice_of_dimensions_finds_the_family_rank():
    """Twelve fields on three directions (and a little of a field each one alone holds):
    leaving each out and identifying it from 5 noisy beads, three directions do best,
    and its error there is close to what the noise and the miss allow."""
    rng = np.random.default_rng(3)
    base = _model(rng)
    z = rng.standard_normal((12, 3)) * np.sqrt(base.variances)
    fields = np.array([base.field(zk) for zk in z]) + _smooth_fields(rng, 12, 0.002)
    beads = []
    for k in range(12):
        c, sd, centers = _beads(base, z[k], rng, n=30, sd=0.01)
        beads.append(Beads(centers, c, sd))
    out = choose_dimensions(fields, beads, GRID, SHAPE, np.eye(N_I))
    table = {row["n"]: row["error"] for row in out["table"] if "curve" not in row}
    assert out["kind"] == "lines" and out["n_directions"] >= 3
    assert table[3] < 0.5 * table[2] and table[3] < 0.25 * table[0]
    assert out["band"]["low"] < out["band"]["median"] < out["band"]["high"]


def test_misses_are_zero_for_fields_on_few_directions():
    rng = np.random.default_rng(4)
    base = _model(rng)
    fields = np.array([base.field(zk) for zk in rng.standard_normal((6, 3))])
    assert np.abs(misses(fields, 3)).max() < 1e-9 * np.abs(fields).max()
    mean, dirs, var = principal(fields)
    assert len(dirs) == 3  # rank 3: the rest of the K - 1 directions are dropped
    model = build_model(fields, 3, GRID, SHAPE, np.eye(N_I))
    assert np.abs(model.miss_cov).max() < 1e-18


def test_relative_field_error_ignores_amplitude():
    rng = np.random.default_rng(5)
    f = _smooth_fields(rng, 1)[0] + 3.0
    assert relative_field_error(2.5 * f, f) < 1e-12
    other = f + 0.1 * _smooth_fields(rng, 1)[0]
    assert relative_field_error(other, f) > 1e-3


def test_relative_field_errors_are_those_of_each_field():
    """The batched errors against the per-field one, a field with a zero node included
    (that node left out of its mean, as the single one leaves it out)."""
    rng = np.random.default_rng(6)
    truth = _smooth_fields(rng, 1)[0] + 3.0
    fields = truth[None] + 0.2 * _smooth_fields(rng, 4)
    fields[2, 7] = 0.0
    got = relative_field_errors(fields, truth)
    unit_t = truth / np.linalg.norm(truth, axis=1, keepdims=True)
    want = []
    for f in fields:  # the definition, node by node
        sq = [np.sum((f[g] / np.linalg.norm(f[g]) - unit_t[g]) ** 2)
              for g in range(len(f)) if np.linalg.norm(f[g]) > 0]
        want.append(np.sqrt(np.mean(sq)))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert relative_field_error(fields[1], truth) == got[1]
    assert len(set(np.round(got, 9))) == 4  # four different fields, four errors


def test_the_nested_solve_is_each_model_solved_alone():
    """Every size at once (:func:`solve_nested`, as the choice of dimensions solves them)
    against :func:`solve_coordinates` on each model's own columns, noisy beads of a
    known field: the same coordinates, zero outside each model's columns. A column left
    in by mistake or solved with the others' amplitudes would move them by far more than
    the alternations' 1e-10 stop."""
    rng = np.random.default_rng(7)
    model = _model(rng)
    c, sd, centers = _beads(model, np.array([1.2, -0.5, 0.4]), rng, sd=0.05,
                            amplitude=np.array([0.8, 1.0, 1.3, 1.1, 0.9]))
    base, a = design(model, centers)
    cw, bw, aw = whitened(model.gram, c, base, a)
    masks = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1], [1, 0, 1]], bool)
    z = solve_nested(cw, bw, aw, sd, model.variances, masks, n_iter=200)
    for row, mask in zip(z, masks, strict=True):
        idx = np.flatnonzero(mask)
        alone, _, _ = solve_coordinates(cw, bw, aw[:, :, idx], sd, model.variances[idx],
                                        n_iter=200)
        np.testing.assert_allclose(row[idx], alone, rtol=1e-8, atol=1e-10)
        assert np.all(row[~mask] == 0.0)
    assert np.abs(z[3] - z[2]).max() > 1e-3  # the sizes differ: not one fit copied


@pytest.mark.parametrize("true_factor", [1.0, 2.2])
def test_the_noise_factor_is_the_beads_scatter_over_their_claimed_noise(true_factor):
    """Four images of 100 beads each on known fields, each bead's coefficients off its
    field by ``true_factor`` times the noise it claims (which varies from bead to
    bead), its amplitude anywhere in 0.5 to 2, three beads a hundred times off (a
    doublet, debris). The sample median of ``q`` over 400 beads (chi-square of 5
    degrees of freedom) has a relative standard error of about 5 %, 2.5 % on the
    factor: it lies within 10 % of the truth."""
    rng = np.random.default_rng(8)
    fields = _smooth_fields(rng, 4) + np.r_[4.0, np.zeros(N_I - 1)]
    from napari_psfspace.core.family.coordinates import bilinear

    beads = []
    for field in fields:
        centers = rng.uniform(0, 255, (100, 2))
        sd = rng.uniform(0.01, 0.05, 100)
        g = rng.uniform(0.5, 2.0, 100)
        c = g[:, None] * (bilinear(GRID, centers) @ field)
        c += true_factor * sd[:, None] * rng.standard_normal(c.shape)
        beads.append(Beads(centers, c, sd))
    beads[0].coefficients[:3] += 100 * beads[0].sd[:3, None]
    got = noise_factor(fields, beads, GRID, np.eye(N_I))
    assert abs(got / true_factor - 1) < 0.10
    # fields it cannot measure give no factor
    assert noise_factor(fields, [None] * 4, GRID, np.eye(N_I)) == 1.0


def test_one_bad_bead_among_five_is_left_out_and_single_beads_are_kept():
    """Five beads of a known field: none is left out; one of them replaced by a PSF the
    field does not hold at that place (its coefficients those of another position and
    condition, as a pair or a saturated core changes them): that one is left out."""
    rng = np.random.default_rng(6)
    model = _model(rng, miss=0.005)
    for trial in range(20):
        z = rng.standard_normal(3) * np.sqrt(model.variances)
        c, sd, centers = _beads(model, z, rng, sd=0.01)
        check = check_beads(model, c, sd, centers)
        assert not check.left_out, (trial, check.scores)
        assert np.nanmax(check.scores) < OUTLIER
        bad = int(rng.integers(5))
        c[bad] = c[bad] + 0.3 * np.abs(c[bad]).max() * rng.standard_normal(N_I)
        check = check_beads(model, c, sd, centers)
        assert check.left_out == [bad], (trial, check.scores)


def test_few_beads_are_not_judged():
    rng = np.random.default_rng(7)
    model = _model(rng)
    c, sd, centers = _beads(model, np.zeros(3), rng, n=3, sd=0.01)
    check = check_beads(model, c, sd, centers)
    assert check.keep.all() and np.isnan(check.scores).all()


@pytest.mark.parametrize("n_l", [0, 1, 3])
def test_any_number_of_directions_fits(n_l):
    rng = np.random.default_rng(8)
    model = _model(rng)
    c, sd, centers = _beads(model, np.zeros(3), rng, sd=0.01)
    fit = fit_coordinates(model, c, sd, centers, n_directions=n_l)
    assert fit.z.shape == (n_l,) and fit.cov.shape == (n_l, n_l)
    assert np.all(np.isfinite(fit.residuals))


def test_many_beads_are_judged_by_downdating_the_full_fit(monkeypatch):
    """Beyond MAX_KRIGED_CHECK beads each fit without one bead is the full fit's normal
    equations less its rows: with the amplitudes fixed and no miss to krige, the same
    scores as fitting each subset anew, to round-off."""
    from napari_psfspace.core.restore import bead_check

    rng = np.random.default_rng(9)
    model = _model(rng)
    c, sd, centers = _beads(model, np.array([0.3, -0.2, 0.1]), rng, n=20, sd=0.01)
    fixed = (1.0, 1.0)
    fast = bead_check.leave_one_out(model, c, sd, centers, amplitude_range=fixed)
    monkeypatch.setattr(bead_check, "MAX_KRIGED_CHECK", 100)
    slow = bead_check.leave_one_out(model, c, sd, centers, amplitude_range=fixed)
    np.testing.assert_allclose(fast[0], slow[0], rtol=1e-8)
    np.testing.assert_allclose(fast[1], slow[1], rtol=1e-8)


def test_shape_scores_are_the_noise_for_patches_the_basis_holds():
    """Patches made of the basis plus white noise of a known sd under the window: the
    energy outside the basis is the noise's less what falls in the basis's span (the mean
    of 400 patches within 0.05 of it: each a chi^2 of about 300 degrees of freedom over
    its mean, sd 0.08, their mean's 0.004); a patch holding a shape outside the basis
    scores many times that."""
    from napari_psfspace.core.restore.bead_check import shape_scores

    rng = np.random.default_rng(12)
    size, n_i = 21, 6
    yy, xx = np.indices((size, size)) - size // 2
    window = np.clip(1.0 - np.hypot(yy, xx) / 10.5, 0.0, 1.0)
    flat = np.linalg.qr(rng.standard_normal((size * size, n_i)) * window.reshape(-1, 1))[0]
    basis = flat.T.reshape(n_i, size, size)
    coef = rng.standard_normal((400, n_i))
    sd = 0.01
    psf = np.einsum("pi,ixy->pxy", coef, basis) + sd * window * rng.standard_normal(
        (400, size, size))
    c = np.einsum("pxy,ixy->pi", psf, basis)  # orthonormal: the least squares
    got = shape_scores(psf, c, basis, np.full(400, sd), window)
    w2 = float((window ** 2).sum())
    # the noise's energy (sd w)^2 less what falls in the basis's span
    taken = sum(float((basis[i] ** 2 * window ** 2).sum()) for i in range(n_i))
    assert abs(got.mean() - (w2 - taken) / w2) < 0.05
    odd = psf[:1] + 0.2 * np.roll(psf[:1], 4, axis=2)  # a second bead beside it
    odd_c = np.einsum("pxy,ixy->pi", odd, basis)
    assert shape_scores(odd, odd_c, basis, np.full(1, sd), window)[0] > 5 * got.mean()


def test_a_disagreeing_bead_of_a_single_shape_is_kept():
    """A bead the others do not predict (the family misses the image there) but of a
    single bead's shape keeps its information: left out only when its shape is odd."""
    rng = np.random.default_rng(13)
    model = _model(rng, miss=0.005)
    c, sd, centers = _beads(model, np.zeros(3), rng, sd=0.01)
    c[2] = c[2] + 0.3 * np.abs(c[2]).max() * rng.standard_normal(N_I)
    single = check_beads(model, c, sd, centers, shapes=np.ones(5))
    assert single.left_out == [] and single.scores[2] > OUTLIER
    odd = check_beads(model, c, sd, centers, shapes=np.array([1.0, 1.0, 6.0, 1.0, 1.0]))
    assert odd.left_out == [2]
