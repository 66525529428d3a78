"""The 3D operator on lateral blocks (``core/volume/blocks3d``) and the deconvolution on
tiles, in memory and through dask (``core/volume/tiles3d``)."""

import numpy as np
import pytest

from napari_psfspace.core.volume.blocks3d import BlockedOperator3D
from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
from napari_psfspace.core.volume.operator3d import ProductConvolution3D
from napari_psfspace.core.volume.tiles3d import richardson_lucy_3d_tiled, tile_sizes
from tolerances import U32, product_convolution_3d_errors


def _operator(seed=0, shape=(6, 50, 44), kernel=(5, 7, 7), n=3):
    rng = np.random.default_rng(seed)
    basis = rng.random((n, *kernel))
    gy, gx = np.linspace(0, shape[1] - 1, 5), np.linspace(0, shape[2] - 1, 4)
    return ProductConvolution3D(basis, rng.random((n, 5, 4)), shape=shape, grid=(gy, gx),
                                plane=2)


@pytest.mark.parametrize("block", [7, 16, 50])
def test_exact_blocks_are_the_operator_and_pass_the_dot_test(block):
    op = _operator()
    rng = np.random.default_rng(1)
    u, v = rng.standard_normal((2, *op.image_shape))
    blocked = BlockedOperator3D(op, block=block, rtol=0.0)
    # a block narrower than a grid cell may need fewer kernels, exactly (error 0)
    assert blocked.n_kernels <= op.n_psf and blocked.error == 0.0
    hu, htv = blocked.apply(u, workers=2), blocked.adjoint(v, workers=2)
    assert hu.dtype == htv.dtype == np.float32
    e_hu, e_htv = product_convolution_3d_errors(op, u, v, prec=U32,
                                                fft_shape=blocked.fft_shape(u.shape[0]),
                                                n_blocks=len(blocked.blocks))
    # against the whole-volume operator in float64 (its own rounding is negligible)
    assert np.linalg.norm(hu - op.apply(u)) <= e_hu
    assert np.linalg.norm(htv - op.adjoint(v)) <= e_htv
    bound = np.linalg.norm(v) * e_hu + np.linalg.norm(u) * e_htv
    assert abs(np.vdot(hu.astype(float), v) - np.vdot(u, htv.astype(float))) <= bound
    # the Richardson-Lucy form: multiply_into
    w = np.ones(op.image_shape, np.float32)
    assert np.array_equal(blocked.adjoint(v, multiply_into=w, workers=1),
                          blocked.adjoint(v, workers=1))


def test_compressed_blocks_keep_each_point_within_rtol():
    """A point's image is its PSF: with ``rtol`` the blocks' PSF is within ``rtol`` of the
    model's wherever the point lies (plus float32 rounding), on fewer kernels."""
    op = _operator(seed=3)
    blocked = BlockedOperator3D(op, block=16, rtol=0.05)
    assert blocked.n_kernels < op.n_psf and blocked.error <= 0.05
    eps = 1e3 * U32  # float32 FFTs of a few thousand voxels
    for y, x in [(3, 3), (20, 30), (47, 8), (33, 41)]:
        u = np.zeros(op.image_shape)
        u[2, y, x] = 1.0
        ref = op.apply(u)
        assert np.linalg.norm(blocked.apply(u) - ref) <= (0.05 + eps) * np.linalg.norm(ref)


def test_bad_blocks_are_named():
    op = _operator()
    with pytest.raises(ValueError, match="`block`"):
        BlockedOperator3D(op, block=3)
    with pytest.raises(ValueError, match="`rtol`"):
        BlockedOperator3D(op, rtol=-1)
    with pytest.raises(TypeError, match="`operator`"):
        BlockedOperator3D(np.ones(3))
    with pytest.raises(ValueError, match="`u` must be a volume"):
        BlockedOperator3D(op).apply(np.ones((4, 10, 10)))


def test_rl_on_exact_blocks_is_rl_on_the_whole_volume():
    op = _operator(seed=4)
    rng = np.random.default_rng(2)
    truth = (rng.random(op.image_shape) < 0.02) * 200.0
    stack = rng.poisson(op.apply(truth) + 5).astype(np.float32)
    whole = richardson_lucy_3d(stack, op, n_iter=10, block=None).volume
    blocks = richardson_lucy_3d(stack, op, n_iter=10, block=16, rtol=0.0)
    assert blocks.n_kernels == op.n_psf
    # ten multiplicative steps, each within a few float32 roundings of the other's
    assert np.abs(blocks.volume - whole).max() <= 1e-4 * whole.max()


def test_tile_sizes_cover_the_axis_and_keep_no_sliver():
    assert tile_sizes(100, 40, 14) == (40, 40, 20)
    assert tile_sizes(90, 40, 14) == (40, 50)  # a 10 px tile would be thinner than the halo
    assert tile_sizes(30, 40, 14) == (30,)
    assert sum(tile_sizes(1234, 256, 100)) == 1234


def test_dask_tiles_are_the_loop_over_tiles_and_near_the_whole_volume():
    import dask.array as da

    op = _operator(seed=5, shape=(6, 90, 80))
    rng = np.random.default_rng(3)
    truth = (rng.random(op.image_shape) < 0.01) * 300.0
    stack = rng.poisson(op.apply(truth) + 5).astype(np.float32)
    kw = dict(n_iter=15, tile=40, halo=14, block=None)
    loop = richardson_lucy_3d_tiled(stack, op, use_dask=False, **kw)
    eager = richardson_lucy_3d_tiled(stack, op, **kw)
    lazy = richardson_lucy_3d_tiled(da.from_array(stack, chunks=(6, 30, 30)), op, **kw)
    assert isinstance(lazy, da.Array)
    # the same arithmetic on the same windows: equal to float32 rounding
    np.testing.assert_allclose(eager, loop, rtol=0, atol=1e-5 * loop.max())
    np.testing.assert_allclose(lazy.compute(), loop, rtol=0, atol=1e-5 * loop.max())
    whole = richardson_lucy_3d(stack, op, n_iter=15, block=None).volume
    assert np.linalg.norm(loop - whole) <= 0.02 * np.linalg.norm(whole)
    with pytest.raises(ValueError, match="`halo`"):
        richardson_lucy_3d_tiled(stack, op, tile=20, halo=30)


def _points_f1(v: np.ndarray, truth: np.ndarray, threshold: float) -> float:
    """F1 of the local maxima of ``v`` above ``threshold`` against the true points
    (matched within 1.5 voxels)."""
    from scipy import ndimage as ndi
    from scipy.spatial import cKDTree

    found = np.argwhere((v == ndi.maximum_filter(v, 3)) & (v > threshold))
    true = np.argwhere(truth > 0)
    if not len(found):
        return 0.0
    d, _ = cKDTree(true).query(found)
    tp = int((d <= 1.5).sum())
    precision, recall = tp / len(found), min(tp, len(true)) / len(true)
    return 2 * precision * recall / max(precision + recall, 1e-12)


def test_sparse_smooth_3d_finds_the_points_and_takes_the_background():
    """Points on a sloped background, blurred by a field-varying 3D PSF: the sparse part
    finds the points (F1 >= 0.9, no worse than Richardson-Lucy's maxima), and the smooth
    part seen through H is the background (within 10 % inside the field)."""
    from napari_psfspace.core.volume.fista3d import deblur_3d
    from test_volume import _field_varying_blur

    op = _field_varying_blur()
    rng = np.random.default_rng(5)
    truth = np.zeros(op.image_shape, np.float32)
    n = 120
    truth[rng.integers(2, 7, n), rng.integers(4, 92, n), rng.integers(4, 92, n)] = \
        rng.uniform(500, 1500, n)
    bg = np.broadcast_to(10 + 5 * np.linspace(0, 1, 96)[None, None, :], op.image_shape)
    stack = rng.poisson(op.apply(truth) + bg).astype(np.float32)
    res = deblur_3d(stack, op, grid_step=16, max_iter=150, block=32)
    assert res.sparse.dtype == np.float32 and np.all(res.sparse >= 0)
    f1 = _points_f1(res.sparse, truth, 0.02 * truth.max())
    rl = richardson_lucy_3d(stack, op, n_iter=40, background=12.5, block=None).volume
    assert f1 >= 0.9 and f1 >= _points_f1(rl, truth, 0.05 * truth.max()), f1
    seen = op.apply(res.smooth)[2:-2, 8:-8, 8:-8]
    assert np.abs(seen / bg[2:-2, 8:-8, 8:-8] - 1).mean() <= 0.1
    with pytest.raises(ValueError, match="`grid_step`"):
        deblur_3d(stack, op, grid_step=1)


def test_the_psf_grid_shows_each_kernel_and_its_sections():
    from napari_psfspace.core.volume.views import psf_grid_3d

    op = _operator(seed=6)
    ys, xs, vol, sec_x, sec_y = psf_grid_3d(op, 3, gap=1, gamma=1.0)
    k, p, _ = op.kernel_shape
    assert vol.shape == (k, 3 * p + 2, 3 * p + 2) and sec_x.shape == sec_y.shape
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            kern = np.clip(op.kernel_at(y, x), 0, None)
            tile = vol[:, i * (p + 1):i * (p + 1) + p, j * (p + 1):j * (p + 1) + p]
            np.testing.assert_allclose(tile, kern / kern.max(), rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(sec_y[i * (k + 1):i * (k + 1) + k,
                                             j * (p + 1):j * (p + 1) + p],
                                       tile[:, :, p // 2], rtol=1e-6)
    with pytest.raises(ValueError, match="`n`"):
        psf_grid_3d(op, 0)


def test_the_dask_path_runs_on_a_client():
    """``client=``: the tiles computed on a dask.distributed cluster (here in-process)
    give the loop's result."""
    distributed = pytest.importorskip("distributed")
    op = _operator(seed=7, shape=(6, 60, 60))
    stack = np.random.default_rng(4).poisson(op.apply(np.ones(op.image_shape)) + 5)
    stack = stack.astype(np.float32)
    kw = dict(n_iter=4, tile=30, halo=10, block=None)
    loop = richardson_lucy_3d_tiled(stack, op, use_dask=False, **kw)
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2,
                            dashboard_address=None) as client:
        remote = richardson_lucy_3d_tiled(stack, op, client=client, **kw)
    np.testing.assert_allclose(remote, loop, rtol=0, atol=1e-5 * loop.max())


def _rl_problem(seed=4):
    op = _operator(seed=seed)
    rng = np.random.default_rng(2)
    truth = (rng.random(op.image_shape) < 0.02) * 200.0
    return op, rng.poisson(op.apply(truth) + 5).astype(np.float32)


def test_a_blocked_iteration_yields_after_each_wave_of_blocks():
    """Cancel waits for one wave of blocks, not for a whole iteration: the generator
    yields once per wave in ``apply`` and in ``adjoint`` (one block a thread)."""
    from napari_psfspace.core.volume.deconvolve3d import iter_richardson_lucy_3d

    op, stack = _rl_problem()
    n_blocks = len(BlockedOperator3D(op, block=16).blocks)  # 4 x 3
    records = list(iter_richardson_lucy_3d(stack, op, n_iter=2, block=16, workers=1))
    per_iteration = [r for r in records if r.stage == "iteration"]
    # each iteration: a record before apply and before adjoint, n_blocks waves in
    # each, and its end
    assert len(per_iteration) == 2 * (2 * n_blocks + 3)
    fractions = [r.fraction for r in records]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert sum(r.stage == "setup" for r in records) >= n_blocks  # H^T 1 in waves too
    est = [r for r in records if r.stage == "estimate"]
    assert len(est) == 1 and "iterations at most" in est[0].message


def test_the_stopping_rule_ends_when_the_fit_stops_improving():
    op, stack = _rl_problem()
    full = richardson_lucy_3d(stack, op, n_iter=40, block=16)
    assert full.iterations == 40 and not full.stopped and len(full.changes) == 40
    dev = np.asarray(full.deviances)
    assert len(dev) == 40 and np.all(np.diff(dev) <= 1e-6 * dev[1:])  # RL: the fit improves
    # the rule at the improvement the 15th iterate made: it stops at the first iterate
    # (after the minimum) that improved less, and that iterate is plain RL's
    from napari_psfspace.core.volume.deconvolve3d import MIN_ITERATIONS

    gain = (dev[:-1] - dev[1:]) / dev[1:]  # gain[k - 1]: iterate k against k - 1
    tau = gain[14] * 1.0001
    first = next(k for k in range(MIN_ITERATIONS, 40) if gain[k - 1] < tau)
    got = richardson_lucy_3d(stack, op, n_iter=40, block=16, stop=tau)
    assert got.stopped and got.iterations == first <= 15
    again = richardson_lucy_3d(stack, op, n_iter=first, block=16)
    # the same iterate up to the order the threads add the blocks in (float32)
    assert np.abs(got.volume - again.volume).max() <= 1e-4 * again.volume.max()
    assert got.estimate_s is not None and got.estimate_s > 0
    with pytest.raises(ValueError, match="`stop`"):
        richardson_lucy_3d(stack, op, n_iter=3, stop=-1.0)


def test_the_accelerated_iteration_heads_for_plain_rl_sooner():
    """Biggs-Andrews: after k steps the accelerated estimate lies nearer to plain RL's
    estimate of 4k steps than plain RL's k-th does, and stays non-negative and finite."""
    op, stack = _rl_problem()
    far = richardson_lucy_3d(stack, op, n_iter=40, block=16).volume
    plain = richardson_lucy_3d(stack, op, n_iter=10, block=16).volume
    fast = richardson_lucy_3d(stack, op, n_iter=10, block=16, accelerate=True).volume
    d = lambda v: np.linalg.norm(v - far) / np.linalg.norm(far)  # noqa: E731
    assert np.isfinite(fast).all() and fast.min() >= 0
    assert d(fast) < 0.8 * d(plain), (d(fast), d(plain))


def test_the_adjoint_on_a_region_is_the_whole_adjoint_there_and_zero_elsewhere():
    """A tile's adjoint computes only the blocks that meet it: on the region it is the
    whole adjoint to the bit (the same blocks, the same sums), elsewhere zero; the
    blocks that cut the region's edge count as meeting it."""
    op = _operator(shape=(6, 50, 44))
    v = np.random.default_rng(4).standard_normal(op.image_shape).astype(np.float32)
    b = BlockedOperator3D(op, block=16, rtol=0.0)
    whole = b.adjoint(v, workers=2)
    region = (10, 37, 5, 30)  # cuts blocks on every side
    part = b.adjoint(v, workers=2, region=region)
    inside = (slice(None), slice(10, 37), slice(5, 30))
    assert np.array_equal(part[inside], whole[inside])
    met = np.zeros(op.image_shape[1:], bool)
    met[0:48, 0:32] = True  # the 16 px blocks that meet rows 10-36, columns 5-29
    assert np.all(part[:, ~met] == 0) and np.array_equal(part[:, met], whole[:, met])
