"""Richardson-Lucy on tiles that exchange their margins every iteration
(``core/volume/exchange3d``): the whole volume's result, tile by tile."""

import json

import numpy as np
import pytest

from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
from napari_psfspace.core.volume.exchange3d import (
    iter_richardson_lucy_3d_exchange,
    richardson_lucy_3d_exchange,
    ring_width,
)
from napari_psfspace.core.volume.tiles3d import tile_sizes
from test_volume_blocks import _operator


def _problem(seed=5, shape=(6, 90, 80)):
    op = _operator(seed=seed, shape=shape)
    rng = np.random.default_rng(3)
    truth = (rng.random(op.image_shape) < 0.01) * 300.0
    return op, rng.poisson(op.apply(truth) + 5).astype(np.float32)


@pytest.mark.parametrize("rtol", [0.0, 0.05])
def test_exchanged_tiles_are_the_whole_volume(rtol):
    """Tiles of 32 px (3 x 3 of them, the last ones narrower) on 16 px blocks, 15
    iterations: every voxel within 1e-4 of the whole volume's maximum, seams included
    (the same blocks and kernels; only the order of float32 additions differs, a few
    roundings a step: measured 3e-7). Independent tiles (``tiles3d``) are only held within
    2 % in norm of it (``test_volume_blocks``)."""
    op, stack = _problem()
    whole = richardson_lucy_3d(stack, op, n_iter=15, block=16, rtol=rtol).volume
    tiled = richardson_lucy_3d_exchange(stack, op, n_iter=15, tile=32, block=16, rtol=rtol)
    assert tiled.dtype == np.float32 and tiled.shape == stack.shape
    assert np.abs(tiled - whole).max() <= 1e-4 * whole.max()


def test_the_iterates_can_live_in_a_store(tmp_path):
    import dask.array as da

    op, stack = _problem(shape=(6, 64, 48))
    whole = richardson_lucy_3d(stack, op, n_iter=6, block=16, rtol=0.05).volume
    lazy = run_with_progress(iter_richardson_lucy_3d_exchange(
        da.from_array(stack, chunks=(6, 20, 20)), op, n_iter=6, tile=32, block=16,
        store=tmp_path))
    assert isinstance(lazy, da.Array)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["data", "norm", "ratio", "state.json", "u0", "u1"]
    assert np.abs(lazy.compute() - whole).max() <= 1e-4 * whole.max()


def test_the_tiles_run_on_a_client():
    distributed = pytest.importorskip("distributed")
    op, stack = _problem(shape=(6, 64, 64))
    whole = richardson_lucy_3d(stack, op, n_iter=4, block=16).volume
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2,
                            dashboard_address=None) as client:
        remote = richardson_lucy_3d_exchange(stack, op, n_iter=4, tile=32, block=16,
                                             client=client)
    assert np.abs(remote - whole).max() <= 1e-4 * whole.max()


def test_the_tiles_run_on_two_worker_processes(tmp_path):
    """A real scheduler and two worker processes (``LocalCluster``): the tiles of a pass
    are spread over both, and the result is the whole volume's, with the iterates in the
    cluster's memory or in a store the workers read and write. How much faster two
    workers are is the bench's figure (``deblur3d_scale --scaling``), not a test's."""
    distributed = pytest.importorskip("distributed")
    op, stack = _problem(shape=(6, 64, 128))  # 2 x 4 tiles of 32 px
    whole = richardson_lucy_3d(stack, op, n_iter=3, block=16).volume
    with (distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                   dashboard_address=None) as cluster,
          distributed.Client(cluster) as client,
          distributed.get_task_stream(client) as stream):
        remote = richardson_lucy_3d_exchange(stack, op, n_iter=3, tile=32, block=16,
                                             client=client)
        stored = run_with_progress(iter_richardson_lucy_3d_exchange(
            stack, op, n_iter=3, tile=32, block=16, client=client, store=tmp_path))
        workers = set(client.scheduler_info()["workers"])
    assert np.abs(remote - whole).max() <= 1e-4 * whole.max()
    assert np.abs(np.asarray(stored) - whole).max() <= 1e-4 * whole.max()
    # the window products (each trimmed to its tile in the same task)
    used = {t["worker"] for t in stream.data if "_trim-" in str(t["key"])}
    assert used == workers and len(workers) == 2


def test_the_ring_and_the_tiles():
    assert ring_width(_operator(kernel=(5, 7, 7))) == 3
    assert tile_sizes(90, 32, 0) == (32, 32, 26)
    assert tile_sizes(64, 32, 0) == (32, 32)
    assert tile_sizes(50, 24, 3) == (24, 26)  # a 2 px tile would be narrower than the ring


def test_tiles_that_cut_the_blocks_are_exact_too():
    """Tiles of 24 px on blocks of 16: a window's blocks are the field's cut by it, each
    with its whole block's kernels."""
    op, stack = _problem(shape=(6, 70, 50))
    whole = richardson_lucy_3d(stack, op, n_iter=8, block=16, rtol=0.05).volume
    tiled = richardson_lucy_3d_exchange(stack, op, n_iter=8, tile=24, block=16, rtol=0.05)
    assert np.abs(tiled - whole).max() <= 1e-4 * whole.max()
    with pytest.raises(ValueError, match="`tile`"):
        richardson_lucy_3d_exchange(stack, op, n_iter=1, tile=3, block=16)


def test_an_interrupted_run_resumes_to_the_uninterrupted_result(tmp_path):
    op, stack = _problem(shape=(6, 64, 48))
    kw = dict(tile=32, block=16)
    whole = richardson_lucy_3d_exchange(stack, op, n_iter=6, **kw)
    gen = iter_richardson_lucy_3d_exchange(stack, op, n_iter=6, store=tmp_path, **kw)
    for p in gen:  # stopped after three iterations, as a kill between two would
        if p.stage == "iteration" and p.fraction >= 0.5:
            break
    gen.close()
    state = json.loads((tmp_path / "state.json").read_text())
    assert state["done"] == 3
    with pytest.raises(ValueError, match="cannot resume: the interrupted run had tile 32"):
        run_with_progress(iter_richardson_lucy_3d_exchange(
            stack, op, n_iter=6, store=tmp_path, resume=True, tile=48, block=16))
    done = run_with_progress(iter_richardson_lucy_3d_exchange(
        stack, op, n_iter=6, store=tmp_path, resume=True, **kw))
    # the same iterations from the same stored iterate: the same arithmetic
    assert np.abs(done.compute() - whole).max() <= 1e-6 * whole.max()
    with pytest.raises(ValueError, match="`resume` needs the `store`"):
        run_with_progress(iter_richardson_lucy_3d_exchange(stack, op, resume=True, **kw))


def test_the_plan_fits_the_budget_and_says_when_nothing_does():
    from napari_psfspace.core.volume.exchange3d import BASE_BYTES, plan_for_memory, task_bytes
    from napari_psfspace.core.volume.operator3d import ProductConvolution3D

    rng = np.random.default_rng(0)
    op = ProductConvolution3D(rng.random((4, 31, 41, 41)), rng.random((4, 4, 4)),
                              shape=(64, 2048, 2048), plane=15,
                              grid=(np.linspace(0, 2047, 4), np.linspace(0, 2047, 4)))
    budgets = (1.2e9, 2e9, 4e9)
    plans = [plan_for_memory(op, 64, m, block=256, workers=2) for m in budgets]
    for (tile, n), m in zip(plans, budgets, strict=True):
        assert BASE_BYTES + n * task_bytes(op, 64, tile, 256) <= m
        assert (-(-2048 // tile)) ** 2 >= n  # a tile for every thread
    # 1.2 GB: two tiles of a block at once do not fit; 4 GB: tiles of three blocks fit,
    # and the field is cut in three tiles, 768 px a side (2048 / 3 in whole blocks)
    assert plans == [(256, 1), (256, 2), (768, 2)]
    with pytest.raises(ValueError, match=r"`memory` must be at least 0\.90 GiB for one tile"):
        plan_for_memory(op, 64, 0.8e9, block=256)


def test_a_stack_thinner_than_the_kernel_is_deep():
    """Two planes under kernels five planes deep: a constant map is the plain 'same'
    convolution (zero outside the stack), through the whole-volume operator and its
    blocks, and the exchanged tiles are the whole volume's Richardson-Lucy."""
    from scipy.signal import convolve

    from napari_psfspace.core.volume.blocks3d import BlockedOperator3D
    from napari_psfspace.core.volume.operator3d import ProductConvolution3D

    rng = np.random.default_rng(4)
    h = rng.random((5, 7, 7))
    flat = ProductConvolution3D(h[None], np.ones((1, 2, 2)), shape=(2, 40, 36),
                                grid=(np.array([0.0, 39]), np.array([0.0, 35])), plane=1)
    u = rng.random(flat.image_shape)
    plain = convolve(u, h, mode="same")
    assert np.allclose(flat.apply(u), plain, rtol=0, atol=1e-12 * plain.max())
    blocked = BlockedOperator3D(flat, block=16, rtol=0.0).apply(u)
    assert np.abs(blocked - plain).max() <= 1e-5 * plain.max()  # float32 FFTs
    op = ProductConvolution3D(rng.random((3, 5, 7, 7)), rng.random((3, 5, 4)),
                              shape=(2, 64, 48), plane=1,
                              grid=(np.linspace(0, 63, 5), np.linspace(0, 47, 4)))
    stack = rng.poisson(op.apply((rng.random(op.image_shape) < 0.01) * 300.0) + 5)
    whole = richardson_lucy_3d(stack, op, n_iter=5, block=16).volume
    tiled = richardson_lucy_3d_exchange(stack, op, n_iter=5, tile=32, block=16)
    assert np.abs(tiled - whole).max() <= 1e-4 * whole.max()


def test_in_memory_refuses_a_stack_over_the_memory_available(monkeypatch):
    """Four float32 volumes (eight accelerated) against 80 % of the memory available:
    one line naming the tiled path, before any allocation."""
    from napari_psfspace.core.common import validate

    op, stack = _problem(shape=(6, 64, 48))
    need = 4 * 4 * stack.size
    monkeypatch.setattr(validate, "available_memory", lambda: int(need / 0.8) + 1)
    richardson_lucy_3d(stack, op, n_iter=1, block=16)  # fits
    with pytest.raises(ValueError, match=r"8 float32 volumes.*psfspace deblur3d --memory"):
        richardson_lucy_3d(stack, op, n_iter=1, block=16, accelerate=True)
    monkeypatch.setattr(validate, "available_memory", lambda: int(need / 0.8) - 1)
    with pytest.raises(ValueError, match=r"4 float32 volumes"):
        richardson_lucy_3d(stack, op, n_iter=1, block=16)


def test_the_stack_is_read_by_its_own_chunks_once_each(tmp_path):
    """A dask stack of chunks narrower than a tile is read a whole chunk at a time, each
    once (a compressed chunk is not decompressed once a tile it meets), in slabs of
    whole z chunks no larger than a tile; the store's data is the stack clipped at 0.
    Chunks larger than a tile are read by the tiles."""
    import dask.array as da

    from napari_psfspace.core.volume.exchange_store import _read_boxes, open_array, write_data

    rng = np.random.default_rng(1)
    stack = (rng.random((6, 40, 50)) - 0.2).astype(np.float32)
    lazy = da.from_array(stack, chunks=(1, 16, 16))
    edges_y, edges_x = [(0, 24), (24, 40)], [(0, 24), (24, 48), (48, 50)]
    boxes = _read_boxes(lazy, edges_y, edges_x)
    seen = np.zeros(stack.shape, int)
    z_ends, y_ends, x_ends = ({0, *np.cumsum(c).tolist()} for c in lazy.chunks)
    for zs, ys, xs in boxes:
        seen[slice(*zs), slice(*ys), slice(*xs)] += 1
        assert set(zs) <= z_ends and set(ys) <= y_ends and set(xs) <= x_ends
        assert (zs[1] - zs[0]) * 16 * 16 <= 6 * 24 * 24  # a tile's volume at most
    assert np.all(seen == 1)
    assert len(boxes) < lazy.numblocks[0] * lazy.numblocks[1] * lazy.numblocks[2]
    big = da.from_array(stack, chunks=(6, 40, 50))
    assert _read_boxes(big, edges_y, edges_x) == [((0, 6), ys, xs) for ys in edges_y
                                                  for xs in edges_x]
    for source in (lazy, stack):
        folder = tmp_path / str(type(source).__name__)
        folder.mkdir()
        open_array(folder, "data", stack.shape, 8, create=True)
        write_data(source, folder, edges_y, edges_x, chunk=8, workers=2)
        got = open_array(folder, "data", stack.shape, 8)[:, :, :]
        assert np.array_equal(got, np.clip(stack, 0, None))


def test_a_raw_volume_is_written_and_read_by_boxes_across_its_chunks(tmp_path):
    """The work folder's arrays: a float32 ``.npy`` of lateral chunks (numpy reads it),
    every box written is read back across the chunks it meets, the field's padding and
    the rest read 0; a file that is not this volume's is named."""
    from napari_psfspace.core.volume.exchange_store import RawVolume

    vol = RawVolume(tmp_path / "v", (3, 20, 30), 8, create=True)
    rng = np.random.default_rng(0)
    a = rng.random((3, 7, 11)).astype(np.float32)
    vol[:, 2:9, 5:16] = a
    vol[:, 9:20, :] = 2.0
    b = rng.random((3, 16, 16)).astype(np.float32)
    vol[:, 0:16, 8:24] = b  # four whole chunks: one run of bytes each, no mapping
    vol[1:3, 0:8, 24:30] = 3.0  # planes of a chunk cut by the field's edge
    vol[1:2, 8:16, 16:24] = 4.0  # a plane of a whole chunk: a run of bytes
    want = np.zeros((3, 20, 30), np.float32)
    want[:, 2:9, 5:16], want[:, 9:, :] = a, 2.0
    want[:, 0:16, 8:24] = b
    want[1:3, 0:8, 24:30], want[1:2, 8:16, 16:24] = 3.0, 4.0
    chunks = np.load(tmp_path / "v")  # (3, 4, 3, 8, 8): the field padded to 24 x 32
    assert chunks.shape == (3, 4, 3, 8, 8)
    assert np.array_equal(chunks[1, 2][:, 0:4, 0:4], want[:, 8:12, 16:20])
    assert np.array_equal(chunks[0, 1], b[:, 0:8, 0:8])
    again = RawVolume(tmp_path / "v", (3, 20, 30), 8)
    assert np.array_equal(again[:, :, :], want)
    assert np.array_equal(again[1:3, 1:10, 4:17], want[1:3, 1:10, 4:17])
    assert np.array_equal(again[1:3, 8:16, 8:24], want[1:3, 8:16, 8:24])
    with pytest.raises(ValueError, match="is not a float32 volum"):
        RawVolume(tmp_path / "v", (3, 20, 30), 16)
