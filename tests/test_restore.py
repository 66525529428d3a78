"""Blind deblurring (core/restore, issue 12; paper, Appendix D): identifying an operator
of a family from a few beads, and the sparse + smooth deconvolution."""

import warnings

import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.model.operator import ProductConvolution
from napari_psfspace.core.restore.deconvolve import deblur, iter_deblur
from napari_psfspace.core.restore.fista import BlockFista
from napari_psfspace.core.restore.identify import (
    MIN_BEADS_JUDGED,
    IdentificationWarning,
    identify_operator,
    solve_identification,
)
from napari_psfspace.core.restore.smooth_grid import SmoothGrid
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.stacks import random_conditions, simulate_stack, within
from tolerances import U32, U64, abs_dot, gamma, sum_error

LOW = {"amplitude": (4e3, 1.2e4)}  # bead photons x0.2 of the default: noisy beads


def _gaussian_operator(shape, sigma=2.5, half=12):
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    psf = np.exp(-(yy**2 + xx**2) / (2 * sigma**2))
    psf /= psf.sum()
    h, w = shape
    return ProductConvolution(psf[None], np.ones((1, 2, 2)), shape=shape,
                              grid=(np.array([0.0, h - 1]), np.array([0.0, w - 1])))


def _point_scene(seed=0, shape=(256, 256), n=60):
    rng = np.random.default_rng(seed)
    h, w = shape
    truth = np.zeros(shape, np.float32)
    pts = np.round(rng.uniform(10, h - 10, (n, 2)))
    amps = rng.uniform(500, 2000, n)
    for (y, x), a in zip(pts.astype(int), amps, strict=True):
        truth[y, x] += a
    bg = (100 + 50 * np.sin(np.linspace(0, 3, w))[None, :]
          * np.cos(np.linspace(0, 2, h))[:, None]).astype(np.float32)
    op = _gaussian_operator(shape)
    clean = op.apply(truth) + op.apply(bg)
    image = rng.poisson(np.clip(clean, 0, None)).astype(np.float32)
    return image, op, truth, pts, bg


def test_smooth_grid_is_nonnegative_with_its_adjoint():
    rng = np.random.default_rng(0)
    g = SmoothGrid((97, 130), 12)
    w = rng.random(g.grid_shape).astype(np.float32)
    # mean 1: <U w, u> is not a cancelled sum, so that the bound below is far under it
    u = (1 + rng.standard_normal((97, 130))).astype(np.float32)
    uw, utu = g.synthesis(w), g.adjoint(u)
    assert uw.dtype == np.float32 and utu.dtype == np.float32
    # dot test: the inner products in float64, so that only the operator's float32
    # rounding enters; bounded term by term (tests/tolerances.py): U w sums ny then nx
    # products per pixel, U^T u sums up to H then W per node, all weights >= 0
    lhs = np.vdot(uw.astype(np.float64), u.astype(np.float64))
    rhs = np.vdot(w.astype(np.float64), utu.astype(np.float64))
    ry, rx = g.ry.astype(np.float64), g.rx.astype(np.float64)
    size_uw = ry @ np.abs(w.astype(np.float64)) @ rx.T  # |U| |w|
    size_utu = ry.T @ np.abs(u.astype(np.float64)) @ rx  # |U^T| |u|
    ny, nx = g.grid_shape
    bound = (gamma(ny + nx) * abs_dot(size_uw, u) + gamma(97 + 130) * abs_dot(w, size_utu)
             + gamma(2 * u.size, U64) * (abs_dot(uw, u) + abs_dot(w, utu)))
    assert abs(lhs - rhs) <= bound
    assert bound < 1e-3 * abs(lhs)  # the test can fail: a wrong adjoint is off by ~|lhs|
    assert g.synthesis(w).min() >= 0  # u2 = U w >= 0 wherever w >= 0
    v = rng.standard_normal(g.grid_shape)
    assert np.vdot(g.laplacian(w.astype(float)), v) == pytest.approx(
        np.vdot(w, g.laplacian(v)))  # symmetric
    assert np.allclose(g.laplacian(np.ones(g.grid_shape)), 0)  # constants are smooth
    # the exact ||U||^2 bounds ||U w||^2 / ||w||^2
    assert np.linalg.norm(g.synthesis(w)) ** 2 <= g.norm2() * np.linalg.norm(w) ** 2 * 1.0001


def test_block_fista_solves_a_nonnegative_lasso():
    from scipy.optimize import nnls

    rng = np.random.default_rng(1)
    a = rng.standard_normal((40, 15))
    x_true = np.maximum(rng.standard_normal(15), 0)
    b = a @ x_true + 0.01 * rng.standard_normal(40)
    lam = 0.0  # with no l1 weight: the non-negative least squares solution
    big = float(np.linalg.norm(a, 2) ** 2)

    def gradient(x):
        r = a @ x[0] - b
        return [a.T @ r], 0.5 * float(r @ r)

    solver = BlockFista(gradient, [lambda v, t, rows: np.maximum(v - lam * t, 0)], [big])
    solver.setup([np.zeros(15)])
    assert list(solver.run(5000, 1e-12))[-1][0] < 5000  # stopped on the iterate's change
    ref, _ = nnls(a, b)
    np.testing.assert_allclose(solver.finalize()[0], ref, atol=1e-6)
    # float32 blocks stay float32 through the momentum (a NumPy float64 scalar would
    # promote them: NEP 50), so that the FFTs run in single precision
    a32, b32 = a.astype(np.float32), b.astype(np.float32)
    solver = BlockFista(lambda x: ([a32.T @ (a32 @ x[0] - b32)], 0.0),
                        [lambda v, t, rows: np.maximum(v, 0)], [big])
    solver.setup([np.zeros(15, np.float32)])
    list(solver.run(20, 0.0))
    assert solver.finalize()[0].dtype == np.float32 and solver.z[0].dtype == np.float32


def test_deblur_finds_the_points_and_the_background():
    image, op, truth, pts, bg = _point_scene()
    res = deblur(image, op)
    assert res.sparse.dtype == np.float32 and res.smooth.shape == image.shape
    assert res.sparse.min() >= 0 and res.smooth.min() >= 0
    assert res.converged and res.iterations < 300  # measured 148
    from skimage.feature import peak_local_max

    peaks = peak_local_max(res.sparse, min_distance=2, threshold_abs=50.0)
    d, i = cKDTree(pts).query(peaks)
    recall = len(set(i[d <= 1.5])) / len(pts)
    precision = float(np.mean(d <= 1.5))
    # measured: recall 0.92 (pairs closer than the blur merge), precision 0.948 (3 of
    # 58 peaks); bench_deblur's scenes: 0.92-0.98 and 0.98
    assert recall >= 0.88 and precision >= 0.93, (recall, precision)
    # the background to within a tenth of the noise (sd 10): measured 0.53
    assert np.abs(res.smooth - bg).mean() < 1.5
    # the objective went down
    assert res.objective[-1] < 0.5 * res.objective[0]


def test_saturated_pixels_bound_the_fit_from_below():
    image, op, truth, pts, _ = _point_scene()
    y0, x0 = pts[0].astype(int)
    bright = np.zeros_like(truth)
    bright[y0, x0] = 20000  # one bead much brighter than the rest
    img = image + op.apply(bright)
    level = 0.5 * float(np.percentile(img, 99.99))
    clipped = np.minimum(img, level)
    assert (img >= level).sum() == 45

    def flux(res):
        return ndi.uniform_filter(res.sparse.astype(float), 5)[y0, x0] * 25

    full = flux(deblur(img, op))  # measured 22012 (the point holds 21016)
    fitted = flux(deblur(clipped, op))  # a float image: no level known, none assumed
    res = deblur(clipped, op, saturation=level)
    assert res.parameters["saturated_pixels"] == 45
    # measured: 8100 fitted as measured, 16907 as lower bounds
    assert fitted < 0.45 * full and flux(res) > 0.7 * full, (fitted, flux(res), full)
    # integer images: the dtype's maximum by default; too much of it is an error
    u16 = np.round(clipped).astype(np.uint16)
    assert deblur(u16, op, max_iter=3).parameters["saturation"] == 65535
    with pytest.raises(ValueError, match="saturation level 100"):
        deblur(clipped, op, saturation=100.0, max_iter=3)


def test_the_refit_gives_the_points_their_flux_back_and_raises_spurious_ones():
    # exact operator, 500-2000-photon points: the l1 term alone keeps 0.72-0.79 of each
    # point's flux (median over seeds 0-2); refitted per cluster, 1.05-1.08
    image, op, truth, pts, _ = _point_scene()
    at = tuple(pts.T.astype(int))

    def flux(sparse):  # within 2 px of each true point, over its true amplitude
        return np.median(ndi.uniform_filter(sparse.astype(float), 5)[at] * 25 / truth[at])

    raw = deblur(image, op)
    res = deblur(image, op, debias=True)
    assert not raw.parameters["debias"] and "debias_iterations" not in raw.parameters
    assert flux(raw.sparse) < 0.85 and 0.95 <= flux(res.sparse) <= 1.15
    np.testing.assert_array_equal(res.sparse > 0, raw.sparse > 0)  # the same points
    p = res.parameters
    assert p["debias"] and p["debias_converged"] and 0 < p["debias_iterations"] < 100
    # a ratio of two float32 sums: each within sum_error of the exact one
    rel = (sum_error(res.sparse) / res.sparse.sum(dtype=np.float64)
           + sum_error(raw.sparse) / raw.sparse.sum(dtype=np.float64))
    assert p["amplitude_gain"] == pytest.approx(
        res.sparse.sum(dtype=np.float64) / raw.sparse.sum(dtype=np.float64), rel=rel)
    # why it is off by default: points far (> 5 px) from every true point, which the
    # l1 term kept faint (measured <= 61), rise to the level of the real ones
    far = cKDTree(pts).query(np.argwhere(raw.sparse > 0))[0] > 5
    spurious_raw = raw.sparse[raw.sparse > 0][far].max()
    spurious = res.sparse[raw.sparse > 0][far].max()
    assert spurious_raw < 100 and spurious > 200, (spurious_raw, spurious)


def test_deblur_is_a_generator_that_can_stop_and_checks_its_input():
    image, op, *_ = _point_scene(n=5, shape=(96, 96))
    gen = iter_deblur(image, op, max_iter=50)
    first = next(gen)
    assert first.stage == "setup"
    gen.close()  # cancelled between iterations: nothing else runs
    with pytest.raises(ValueError, match="shape"):
        deblur(image[:90], op)
    bad = image.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN|finite"):
        deblur(bad, op)
    with pytest.raises(ValueError, match="sparse_weight"):
        deblur(image, op, sparse_weight=-1.0)


def test_solve_identification_recovers_the_cone_weights():
    rng = np.random.default_rng(3)
    v = rng.random((6, 8, 4))  # K = 6 operators, P = 8 beads, I = 4
    lam = np.array([0.0, 0.7, 0.0, 0.3, 0.0, 0.0])
    g = rng.uniform(0.8, 1.25, 8)
    c = g[:, None] * np.tensordot(lam, v, axes=1)
    weights, amps, history = solve_identification(c, v)
    m = np.tensordot(weights, v, axes=1)
    # the product g Gamma is identified (the scale trades between g and lambda)
    np.testing.assert_allclose(amps[:, None] * m, c, atol=1e-6)
    assert history[-1] <= history[0]
    with pytest.raises(ValueError, match="amplitude_range"):
        solve_identification(c, v, amplitude_range=(2.0, 3.0))


@pytest.fixture(scope="module")
def family():
    """A family learnt from 16 images, and 3 images under conditions it never saw, within
    the range of those it saw (beyond it, the family extrapolates: a tilt of 3 sd gave
    0.134 with every bead against 0.061 for the image alone)."""
    images, truths, seen = simulate_stack(16, (384, 384), 24, seed=0, **LOW)
    r = int(np.median([t.psf_radius for t in truths]))
    sub = estimate_family(images, psf_radius=r, holdout=None)
    draws = random_conditions(40, seed=11)
    unseen = [c for c, ok in zip(draws, within(draws, seen), strict=True) if ok][:3]
    new, new_truths, _ = simulate_stack(3, (384, 384), 24, seed=11, conditions=unseen,
                                        **LOW)
    return sub, r, new, new_truths


def test_five_beads_identify_the_operator_of_a_new_image(family):
    sub, r, new, truths = family
    rng = np.random.default_rng(0)
    ratios, paper_ratios, covered = [], [], []
    dims = sub.metadata["dimensions"]
    assert 1 <= dims["n_directions"] <= sub.n_images - 2 and dims["band"]["n"] > 0
    for image, truth in zip(new, truths, strict=True):
        alone = np.mean(grid_errors(estimate_operator(image, psf_radius=r), truth, n=4))
        inner = truth.positions[(truth.positions.min(axis=1) > 2 * r)
                                & (truth.positions.max(axis=1) < 384 - 2 * r)]
        for _ in range(3):  # three sets of five clicks on each image
            five = inner[rng.choice(len(inner), 5, replace=False)]
            five = five + rng.normal(0, 0.5, five.shape)  # clicked, not centred
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                op = identify_operator(image, sub, beads=five)
            info = op.metadata["identification"]
            assert info["n_beads"] >= 4 and len(info["weights"]) == sub.n_images
            assert len(info["coordinates"]) == info["n_directions"] == dims["n_directions"]
            assert info["choice"] is None  # too few beads to judge against the image's own
            # the warning is issued exactly when the metadata holds one
            assert (info["warning"] is not None) == any(
                issubclass(w.category, IdentificationWarning) for w in caught)
            assert 0 < info["psf_spread"] < 1 and info["left_out"] == []
            lo, hi = info["error_band"]
            error = np.mean(grid_errors(op, truth, n=4))
            covered.append(lo <= error <= hi)
            ratios.append(error / alone)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", IdentificationWarning)
                paper = identify_operator(image, sub, beads=five, prior=False)
            assert np.all(np.asarray(paper.metadata["identification"]["weights"]) >= 0)
            paper_ratios.append(np.mean(grid_errors(paper, truth, n=4)) / alone)
    # issue 12: at most 1.5x the error of estimate_operator on all the beads
    assert np.mean(ratios) <= 1.5, ratios
    # no worse than the paper's cone beyond the scatter of five noisy beads: the paired
    # differences' mean within two standard errors
    diff = np.asarray(ratios) - np.asarray(paper_ratios)
    se = diff.std(ddof=1) / np.sqrt(len(diff))
    assert diff.mean() <= 2 * se, (ratios, paper_ratios)
    # the 90 % band holds the true error: were it right 90 % of the time, 5 or fewer of
    # 9 would happen with probability 0.008
    assert sum(covered) >= 6, covered


def test_identification_warns_when_the_family_cannot_explain_the_beads(family):
    """Bright beads of an image 0.4 waves out of focus, twice the range the family
    learnt: the identified operator misses them, and says so."""
    from napari_psfspace.core.simulation.stacks import Condition

    sub, r, _, _ = family
    far = [Condition(0.4, 0.0, 0.0, 0.0)]
    image, truths, _ = simulate_stack(1, (384, 384), 10, seed=5, conditions=far,
                                      amplitude=(2e4, 3e4))
    inner = truths[0].positions[(truths[0].positions.min(axis=1) > 2 * r)
                                & (truths[0].positions.max(axis=1) < 384 - 2 * r)][:5]
    with pytest.warns(IdentificationWarning, match="does not explain the clicked beads"):
        op = identify_operator(image[0], sub, beads=inner)
    info = op.metadata["identification"]
    assert info["model_error"] > info["warning_bound"] and "bound" in info["warning"]
    # and says where one more bead would help most, inside the field
    y, x = info["more_beads_at"]
    assert "one more bead would help most near" in info["warning"]
    assert 0 < y < 383 and 0 < x < 383
    # within the range, from every bead: a far smaller miss (at the family's bound
    # there: without held-out figures it is a fixed 0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        near = identify_operator(family[2][0], sub).metadata["identification"]
    assert near["model_error"] < info["model_error"] / 3


def _pasted_pair(image, pos, r):
    """``image`` with an unresolved pair (two copies of a bead 6 px apart) pasted into
    the empty place farthest from every bead, and the pair's centre."""
    g = np.arange(3 * r, 384 - 3 * r, 2)
    cand = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    dst = cand[np.argmax(cKDTree(pos).query(cand)[0])]
    inner = pos[(pos.min(axis=1) > 2 * r) & (pos.max(axis=1) < 384 - 2 * r)]
    src = np.round(inner[0]).astype(int)
    h = 2 * r
    piece = image[src[0] - h:src[0] + h + 1, src[1] - h:src[1] + h + 1] - np.median(image)
    pasted = image.copy()
    pasted[dst[0] - h:dst[0] + h + 1, dst[1] - h:dst[1] + h + 1] += piece + ndi.shift(
        piece, (0, 6), order=1)
    return pasted, dst + np.array([0.0, 3.0])


def test_a_clicked_pair_of_beads_is_left_out_and_named(family):
    """Four single beads of a bright image within the family's range, and a fifth click
    on an unresolved pair: the pair is left out (the warning names it), and the
    operator is the one the four single beads give; five single beads lose none."""
    from napari_psfspace.core.restore.bead_check import OUTLIER
    from napari_psfspace.core.simulation.stacks import Condition

    sub, r, _, _ = family
    images, truths, _ = simulate_stack(1, (384, 384), 16, seed=12,
                                       conditions=[Condition(0.0, 0.0, 0.0, 0.0)],
                                       amplitude=(2e4, 3e4))  # bright: a small noise floor
    image, pos = images[0].astype(np.float64), truths[0].positions
    inner = pos[(pos.min(axis=1) > 2 * r) & (pos.max(axis=1) < 384 - 2 * r)]
    pasted, pair = _pasted_pair(image, pos, r)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        real = identify_operator(image, sub, beads=inner[1:6]).metadata["identification"]
        four = identify_operator(pasted, sub, beads=inner[1:5])
    assert real["left_out"] == []
    with pytest.warns(IdentificationWarning, match="disagrees with the others"):
        op = identify_operator(pasted, sub, beads=np.vstack([inner[1:5], pair]))
    info = op.metadata["identification"]
    assert len(info["left_out"]) == 1 and info["n_beads"] == 4
    gone = info["left_out"][0]
    assert np.hypot(*(np.asarray(gone["position"]) - pair)) < 1.5
    assert f"({gone['position'][0]:.0f}, {gone['position'][1]:.0f})" in info["warning"]
    assert gone["score"] > OUTLIER
    # the four beads' centres move by 2e-5 px when the pair's light is in the image
    # being centred (their patches by 4e-7 of a peak of about 0.03): the same operator
    # to 1e-4
    diff = np.linalg.norm(op.coefficients - four.coefficients)
    assert diff < 1e-4 * np.linalg.norm(four.coefficients)


def test_many_beads_identify_no_worse_than_the_image_alone(family):
    """With many beads the identified operator is judged against the image's own
    estimate on held-out beads, and blended with it (issue 24: never worse than the
    simpler baseline). An image 0.3 waves out of focus, beyond the range the family
    learnt, with 24 bright beads: the family's operator alone misses it."""
    from napari_psfspace.core.simulation.stacks import Condition

    sub, r, _, _ = family
    image, truths, _ = simulate_stack(1, (384, 384), 24, seed=6,
                                      conditions=[Condition(0.3, 0.0, 0.0, 0.0)],
                                      amplitude=(2e4, 3e4))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        op = identify_operator(image[0], sub)
    info = op.metadata["identification"]
    assert info["n_beads"] >= MIN_BEADS_JUDGED and info["choice"]["family_weight"] < 1.0
    alone = np.mean(grid_errors(estimate_operator(image[0], psf_radius=r), truths[0], n=4))
    identified = np.mean(grid_errors(sub.operator_from(np.asarray(info["gamma"]),
                                                       project=False), truths[0], n=4))
    kept = np.mean(grid_errors(op, truths[0], n=4))
    print(alone, identified, kept)
    assert identified > 1.3 * alone  # the case the judgement is for
    assert kept <= 1.1 * alone


def test_identification_refuses_what_it_cannot_do(family):
    sub, r, new, _ = family
    with pytest.raises(ValueError, match="shape"):
        identify_operator(new[0][:300], sub)
    with pytest.raises(ValueError, match="inside the image"):
        identify_operator(new[0], sub, beads=np.array([[10.0, 500.0]]))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        identify_operator(new[0], sub, beads=np.zeros((3, 3)))
    flat = np.random.default_rng(0).normal(100, 3, new[0].shape)
    with pytest.raises(ValueError, match="no usable bead"):
        identify_operator(flat, sub)
    with pytest.raises(ValueError, match="patches"):
        identify_operator(new[0], sub, psf_radius=r + 6)


def test_cli_deblur_with_a_subspace_and_clicked_beads(family, tmp_path):
    import tifffile

    from napari_psfspace.cli import main

    sub, r, new, truths = family
    path = tmp_path / "family.npz"
    sub.save(path)
    image = tmp_path / "image.tif"
    tifffile.imwrite(image, new[0])
    beads = tmp_path / "beads.csv"
    inner = truths[0].positions[(truths[0].positions.min(axis=1) > 2 * r)
                                & (truths[0].positions.max(axis=1) < 384 - 2 * r)][:6]
    rows = "\n".join(f"{i},{y},{x}" for i, (y, x) in enumerate(inner))
    beads.write_text("index,axis-0,axis-1\n" + rows + "\n")  # napari's Points CSV
    out = tmp_path / "out.tif"
    assert main(["deblur", str(image), "--family", str(path), "--beads", str(beads),
                 "-o", str(out), "--parts", "-q", "--max-iter", "40"]) == 0
    got = tifffile.imread(out)
    assert got.shape == new[0].shape and got.dtype == np.float32 and got.min() >= 0
    sparse = tifffile.imread(tmp_path / "out.sparse.tif")
    smooth = tifffile.imread(tmp_path / "out.smooth.tif")
    # the sum of the two float32 parts, rounded once
    np.testing.assert_allclose(sparse + smooth, got, rtol=2 * U32, atol=0)
    # the beads are where the sparse part is
    for y, x in inner:
        assert sparse[int(round(y)) - 2:int(round(y)) + 3,
                      int(round(x)) - 2:int(round(x)) + 3].sum() > 0
    # a single model is used as it is; --beads goes with a family only (and --subspace,
    # the deprecated name of --family, still refuses a model file)
    model = tmp_path / "model.npz"
    sub.operator(0).save(model)
    assert main(["deblur", str(image), "--model", str(model), "--beads", str(beads),
                 "-o", str(out), "-q"]) == 2
    assert main(["deblur", str(image), "--subspace", str(model), "-o", str(out), "-q"]) == 2


def test_a_saved_family_identifies_as_the_one_learnt(family, tmp_path):
    """The family's model (its curve or its lines, ``metadata["dimensions"]``) is
    rebuilt from the file: the same beads give the same operator, bit for bit but for
    the model's rebuild (the same arithmetic on the same arrays)."""
    from napari_psfspace.core.family.dimensions import family_model
    from napari_psfspace.core.family.result import OperatorFamily

    sub, r, new, truths = family
    path = tmp_path / "family.npz"
    sub.save(path)
    back = OperatorFamily.load(path)
    dims = sub.metadata["dimensions"]
    assert back.metadata["dimensions"]["kind"] == dims["kind"]
    model, again = family_model(sub), family_model(back)
    assert type(model) is type(again)
    if dims["kind"] == "curve":
        np.testing.assert_array_equal(again.thetas, model.thetas)
        assert again.miss_factor == model.miss_factor == dims["curve"]["miss_factor"]
    inner = truths[1].positions[(truths[1].positions.min(axis=1) > 2 * r)
                                & (truths[1].positions.max(axis=1) < 384 - 2 * r)][:5]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        a = identify_operator(new[1], sub, beads=inner)
        b = identify_operator(new[1], back, beads=inner)
    assert a.metadata["identification"]["kind"] == dims["kind"]
    np.testing.assert_array_equal(b.coefficients, a.coefficients)


def test_points_csv_forms(tmp_path):
    from napari_psfspace.io import read_points_csv

    p = tmp_path / "a.csv"
    p.write_text("index,axis-0,axis-1,axis-2\n0,3,10.5,20\n1,3,11,21.5\n")
    np.testing.assert_allclose(read_points_csv(p), [[10.5, 20], [11, 21.5]])
    p.write_text("10,20\n30,40\n")
    np.testing.assert_allclose(read_points_csv(p), [[10, 20], [30, 40]])
    p.write_text("row,column\n1,2\n")
    np.testing.assert_allclose(read_points_csv(p), [[1, 2]])
    p.write_text("a,b,c\n1,2,3\n")
    with pytest.raises(ValueError, match="axis-0"):
        read_points_csv(p)
    p.write_text("")
    with pytest.raises(ValueError, match="no bead"):
        read_points_csv(p)


def test_sparse_weight_allows_for_the_operators_error_near_bright_sources():
    from napari_psfspace.core.restore.deconvolve import default_weights, model_error_of

    image, op, truth, pts, bg = _point_scene(n=20)
    plain, _, sigma = default_weights(image, op, 50.0)
    assert np.ptp(plain) == 0  # the noise alone: one weight everywhere
    wide, _, _ = default_weights(image, op, 50.0, model_error=0.15)
    far = cKDTree(pts).query(np.argwhere(np.ones(image.shape, bool)))[0].reshape(
        image.shape) > 20
    assert np.allclose(np.median(wide[far]), plain[0, 0], rtol=0.05)  # background: noise
    y, x = pts[0].astype(int)
    assert wide[y, x] > 1.2 * plain[y, x]  # on a source its error adds (measured 1.25x)
    # where the error comes from: the identification, else a model's held-out beads
    assert model_error_of(op) == 0.0
    meta = ProductConvolution(op.basis, op.coefficients, shape=op.image_shape, grid=op.grid,
                              metadata={"heldout": {"residual_mean": 0.05,
                                                    "noise_floor_mean": 0.03}})
    assert model_error_of(meta) == pytest.approx(0.04)


def test_row_helpers_cover_every_row_once_in_order():
    from napari_psfspace.core.common.threads import by_rows_many, map_rows

    out = map_rows(lambda rows: (rows.start, rows.stop), 1000, 2, chunk=32)
    assert out[0] == (0, 32) and out[-1] == (992, 1000)
    assert all(a[1] == b[0] for a, b in zip(out, out[1:], strict=False))
    a, b = np.zeros((600, 3)), np.zeros((300, 5))
    by_rows_many([(lambda x: x.__iadd__(1), (a,)), (lambda x: x.__iadd__(2), (b,))], 2)
    assert (a == 1).all() and (b == 2).all()



def test_clicked_beads_near_the_border_are_kept_with_a_masked_patch(family):
    """Issue 45: a clicked bead whose centre lies between ``r`` and the estimate's border
    rule (``ceil(1.2 r) + 2``) from the edge is kept for the identification (its PSF lies
    in the image; only the window's tail, background, is masked), where the estimate's
    rule drops it."""
    from napari_psfspace.core.common.spacing import bead_border, partial_border
    from napari_psfspace.core.family.patches import image_patches

    sub, r, _, _ = family
    image, truths, _ = simulate_stack(1, (384, 384), 24, seed=7, amplitude=(2e4, 3e4),
                                      border=float(r))
    pos = truths[0].positions
    edge = np.minimum(pos, 383 - pos).min(axis=1)
    near = (edge >= r + 1) & (edge < bead_border(r) - 1)
    assert near.any()  # the scene has such beads (seeded)
    clicked = pos[near]
    kept = image_patches(image[0], r, positions=clicked, border=partial_border(r))
    dropped = image_patches(image[0], r, positions=clicked)
    assert kept.n_beads >= 1 and dropped.n_beads < kept.n_beads
    # and the patch is the bead's: against the truth's PSF there, windowed as patches
    # are, within its noise (each patch's relative noise: its per-pixel noise over its
    # flux, times the window's root sum of squares, over the PSF's norm)
    from napari_psfspace.core.beads.window import bump_window

    p = kept.patches
    win = bump_window(p.size, p.r, p.r_ext)
    truth = np.array([truths[0].psf_at(y, x, p.size) for y, x in p.centers]) * win
    truth /= truth.sum(axis=(1, 2), keepdims=True)
    norm = np.linalg.norm(truth, axis=(1, 2))
    err = np.linalg.norm(p.psf - truth, axis=(1, 2)) / norm
    noise = p.noise / p.flux * np.sqrt((win ** 2).sum()) / norm
    assert np.all(err < 3 * noise + 0.02), (err, noise)


def test_the_judgement_leans_to_the_identified_operator_with_few_beads():
    """The prior of the held-out judgement: an image with as many beads as the family's
    images leans as they do (the even blend), one with none to the identified operator,
    and the lean falls with the square of the image's share of the family's typical
    count between (half the beads: a quarter of the way to the even blend)."""
    from types import SimpleNamespace

    from napari_psfspace.core.family.choice import PRIOR_WEIGHT
    from napari_psfspace.core.restore.identify import judged_prior

    fam = SimpleNamespace(metadata={"beads_per_image": [140, 150, 160]})
    assert judged_prior(fam, 150) == PRIOR_WEIGHT
    assert judged_prior(fam, 400) == PRIOR_WEIGHT
    assert judged_prior(fam, 0) == 1.0
    leans = [judged_prior(fam, n) for n in (15, 30, 75, 120)]
    assert all(a > b for a, b in zip(leans, leans[1:], strict=False))
    assert leans[0] > 0.99 and abs(judged_prior(fam, 75) - 0.875) < 1e-12
