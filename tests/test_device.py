"""The array-module seam (``core/common/device``) and the 3D deblur's device plan, on the
CPU: the choice of device, its one-line errors, the plan's arithmetic, and the device
path of Richardson-Lucy run with NumPy standing in for the device (blocks sized from a
given free memory, volumes on the "device" or kept on the host), equal to the CPU path."""

from dataclasses import dataclass

import numpy as np
import pytest

from napari_psfspace.core.common.device import (
    CPU,
    GPU_EXTRA,
    ArrayModule,
    array_module,
    check_device,
    gpu_status,
)
from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d
from napari_psfspace.core.volume.device_plan import (
    MEMORY_FRACTION,
    block_bytes,
    plan_on_device,
    volume_count,
)
from napari_psfspace.core.volume.operator3d import ProductConvolution3D
from tolerances import U32


def _operator(shape=(6, 96, 80), kernel=(5, 9, 9), n=3, seed=0):
    rng = np.random.default_rng(seed)
    basis = rng.random((n, *kernel))
    basis /= basis.sum(axis=(1, 2, 3), keepdims=True)
    gy, gx = np.linspace(0, shape[1] - 1, 5), np.linspace(0, shape[2] - 1, 4)
    coef = 0.5 + rng.random((n, 5, 4))
    return ProductConvolution3D(basis, coef, shape=shape, grid=(gy, gx), plane=2)


@dataclass(frozen=True)
class NumpyDevice(ArrayModule):
    """NumPy pretending to be a GPU with ``free`` bytes: the device path's arithmetic and
    plan run, its FFTs are scipy's (CuPy's are tested where a GPU is: test_gpu.py)."""

    free: int = 1 << 40

    @property
    def gpu(self) -> bool:
        return True

    def rfftn(self, a, s=None, *, workers=None, overwrite_x=False):
        return CPU.rfftn(a, s, workers=1, overwrite_x=overwrite_x)

    def irfftn(self, a, s, *, workers=None, overwrite_x=False):
        return CPU.irfftn(a, s, workers=1, overwrite_x=overwrite_x)

    def synchronize(self) -> None:
        pass

    def free_bytes(self) -> int:
        return self.free

    def free_cache(self) -> None:
        pass


def test_the_device_is_one_of_three_and_auto_falls_back_to_the_cpu():
    assert array_module("cpu") is CPU
    assert array_module(CPU) is CPU
    for bad in ("cuda", "GPU", None, 0):
        with pytest.raises(ValueError, match="`device` must be one of 'auto', 'cpu', 'gpu'"):
            check_device(bad)
    ok, why = gpu_status()
    if ok:
        pytest.skip("a GPU is here: 'auto' is the GPU (tests/test_gpu.py)")
    assert array_module("auto") is CPU and why
    with pytest.raises(ValueError) as err:
        array_module("gpu")
    line = str(err.value)
    assert "\n" not in line and GPU_EXTRA in line and "`device` = 'gpu'" in line


def test_a_gpu_asked_for_without_one_stops_before_any_work():
    if gpu_status()[0]:
        pytest.skip("a GPU is here")
    op = _operator()
    with pytest.raises(ValueError, match=r"napari-psfspace\[gpu\]"):
        richardson_lucy_3d(np.ones(op.image_shape, np.float32), op, n_iter=1, device="gpu")


def test_the_plan_takes_the_whole_field_when_it_fits_and_smaller_blocks_when_not():
    op = _operator(shape=(6, 1024, 768))
    z = 6
    volumes = volume_count(False) * z * 1024 * 768 * 4
    whole = block_bytes(op, z, 1024)
    plan = plan_on_device(op, z, int((volumes + whole) / MEMORY_FRACTION) + 1)
    assert (plan.block, plan.volumes_on_device) == (1024, True)
    assert plan.bytes == volumes + whole
    # a little less memory: the field in halves, the volumes still on the device
    plan = plan_on_device(op, z, int((volumes + whole) / MEMORY_FRACTION) - 1)
    assert plan.block == 512 and plan.volumes_on_device
    assert plan.bytes <= MEMORY_FRACTION * ((volumes + whole) / MEMORY_FRACTION)
    # memory for the blocks only: the volumes stay on the host (tiles)
    small = block_bytes(op, z, 256)
    plan = plan_on_device(op, z, int(small / MEMORY_FRACTION) + 1)
    assert (plan.block, plan.volumes_on_device) == (256, False)
    # the acceleration's volumes count
    assert volume_count(True) == 2 * volume_count(False)
    with pytest.raises(ValueError, match="GiB free; one block of 256 px"):
        plan_on_device(op, z, int(small / MEMORY_FRACTION) - 1)


@pytest.mark.parametrize("on_device", [True, False])
def test_the_device_path_equals_the_cpu_path(on_device, monkeypatch):
    """The same iterations through the device path: whole field on the "device", or the
    volumes on the host and the blocks copied over (tiles); equal to the CPU's blocks to
    float32 rounding."""
    from napari_psfspace.core.volume import device_plan

    op = _operator()
    rng = np.random.default_rng(1)
    stack = rng.poisson(op.apply(rng.random(op.image_shape) * 200) + 10).astype(np.float32)
    free = 1 << 40
    if not on_device:  # room for blocks of 48 px (the smallest tried here), not volumes
        monkeypatch.setattr(device_plan, "MIN_BLOCK", 48)
        free = int(block_bytes(op, op.image_shape[0], 48) / MEMORY_FRACTION) + 1
    dev = NumpyDevice("gpu", np, free=free)
    got = richardson_lucy_3d(stack, op, n_iter=6, rtol=0.0, device=dev, accelerate=True)
    ref = richardson_lucy_3d(stack, op, n_iter=6, rtol=0.0, device="cpu", accelerate=True)
    assert got.device == "gpu" and ref.device == "cpu"
    assert got.block == (96 if on_device else 48)
    assert isinstance(got.volume, np.ndarray) and got.volume.dtype == np.float32
    # blocks of another size round differently: an FFT's relative rounding over ~1e5
    # voxels grows as sqrt(log2 n) ~ 4 (10 leaves 2.5x for the products around it), and
    # the multiplicative update carries each iteration's rounding on: 6 iterations
    rel = np.linalg.norm(got.volume - ref.volume) / np.linalg.norm(ref.volume)
    assert rel <= 6 * 10 * U32, rel
    assert got.iterations == ref.iterations == 6


# ----------------------------------------------------------------- the 2-D operator and deblur
def _operator_2d(shape=(300, 270), n=3, p=9, seed=0):
    from napari_psfspace.core.model.operator import ProductConvolution

    rng = np.random.default_rng(seed)
    basis = rng.random((n, p, p))
    basis /= basis.sum(axis=(1, 2), keepdims=True)
    gy, gx = np.linspace(0, shape[0] - 1, 4), np.linspace(0, shape[1] - 1, 3)
    return ProductConvolution(basis, 0.5 + rng.random((n, 4, 3)), shape=shape, grid=(gy, gx))


def test_the_2d_operator_on_the_device_path_is_the_cpus():
    """apply, adjoint and the fused data gradient (censored pixels too) through the
    device path (whole arrays, one inverse transform) against the CPU's row-threaded
    path: in float64 both are within a few roundings of the exact result."""
    op = _operator_2d()
    dev = NumpyDevice("gpu", np)
    rng = np.random.default_rng(3)
    u, v = rng.standard_normal((2, *op.image_shape))
    cens = np.nonzero(rng.random(op.image_shape) < 0.05)
    pairs = [(op.apply(u, device=dev), op.apply(u, workers=2)),
             (op.adjoint(v, device=dev), op.adjoint(v, workers=2))]
    for c in (None, cens):
        (g, val), (g0, val0) = (op.data_gradient(u, v, censored=c, device=dev),
                                op.data_gradient(u, v, censored=c, workers=2))
        pairs.append((g, g0))
        assert val == pytest.approx(val0, rel=1e-12)
    for got, ref in pairs:
        assert got.dtype == np.float64
        assert np.linalg.norm(got - ref) <= 1e-12 * np.linalg.norm(ref)
    # the dot test through the device path alone
    lhs, rhs = np.vdot(op.apply(u, device=dev), v), np.vdot(u, op.adjoint(v, device=dev))
    assert abs(lhs - rhs) <= 1e-10 * abs(lhs)
    # its spectra and maps were kept for the device; release() gives them back
    assert op.__dict__.get("_device_cache")
    op.release()
    assert not op.__dict__.get("_device_cache")


def test_the_3d_operator_on_the_device_path_is_the_cpus():
    op = _operator(shape=(5, 40, 36))
    dev = NumpyDevice("gpu", np)
    rng = np.random.default_rng(4)
    u, v = rng.standard_normal((2, *op.image_shape))
    for got, ref in ((op.apply(u, device=dev), op.apply(u)),
                     (op.adjoint(v, device=dev), op.adjoint(v))):
        assert np.linalg.norm(got - ref) <= 1e-12 * np.linalg.norm(ref)
    assert op.__dict__.get("_device_cache")
    op.release()
    assert not op.__dict__.get("_device_cache")


def test_block_fista_on_whole_blocks_is_the_row_chunked_iteration(monkeypatch):
    """On a device BlockFista works on whole blocks (one call, rows = slice(None)); a
    module standing in for the device's (NumPy's functions under another name) takes
    that branch: the same iterates as the CPU's row chunks, in float64."""
    import types

    from napari_psfspace.core.restore import fista

    op = _operator_2d(shape=(300, 64))
    rng = np.random.default_rng(5)
    y = op.apply(rng.random(op.image_shape) * (rng.random(op.image_shape) < 0.01) * 100)

    def gradient(x):
        g, value = op.data_gradient(x[0], y, workers=1)
        return [g], 0.5 * value

    def solve():
        s = fista.BlockFista(gradient,
                             [lambda v, t, rows: np.maximum(v - t * 0.1, 0, out=v)], [1.5],
                             penalty=[lambda v, rows: 0.1 * float(np.abs(v).sum())],
                             workers=2)
        s.setup([np.zeros(op.image_shape)])
        list(s.run(15, 0.0))
        return s.finalize()[0], s.objective

    ref, obj_ref = solve()
    stand_in = types.ModuleType("stand_in")
    stand_in.__dict__.update(np.__dict__)
    monkeypatch.setattr(fista, "namespace", lambda a: stand_in)
    got, obj = solve()
    assert np.linalg.norm(got - ref) <= 1e-12 * np.linalg.norm(ref)
    assert obj == pytest.approx(obj_ref, rel=1e-12)


def _deblur_scene(op, seed=6):
    rng = np.random.default_rng(seed)
    truth = np.zeros(op.image_shape)
    ys, xs = (rng.integers(10, n - 10, 30) for n in op.image_shape)
    truth[ys, xs] = rng.uniform(200, 400, 30)
    return rng.poisson(np.clip(op.apply(truth), 0, None) + 20).astype(np.float32)


def test_deblur_on_the_device_path_is_the_cpus():
    """The 2-D deblur with the transforms on the "device" (the data kept there, the
    iterate on the host): the CPU's result to float32 rounding carried over the
    iterations (a relative 10 U32 per gradient, as the 3D test argues, over at most 60
    iterations; the polish and the support are discrete, and they agree)."""
    from napari_psfspace.core.restore.deconvolve import deblur

    op = _operator_2d()
    image = _deblur_scene(op)
    dev = NumpyDevice("gpu", np)
    got = deblur(image, op, max_iter=60, device=dev)
    ref = deblur(image, op, max_iter=60, device="cpu")
    assert got.parameters["device"] == "gpu" and ref.parameters["device"] == "cpu"
    assert got.iterations == ref.iterations
    assert np.array_equal(got.sparse > 0, ref.sparse > 0)
    rel = np.linalg.norm(got.image - ref.image) / np.linalg.norm(ref.image)
    assert rel <= got.iterations * 10 * U32, rel


@pytest.mark.parametrize("on_device", [True, False])
def test_deblur_3d_on_the_device_path_is_the_cpus(on_device, monkeypatch):
    from napari_psfspace.core.volume import device_plan
    from napari_psfspace.core.volume.fista3d import FISTA_VOLUMES, deblur_3d

    op = _operator()
    rng = np.random.default_rng(7)
    truth = (rng.random(op.image_shape) < 0.002) * rng.uniform(200, 400, op.image_shape)
    stack = rng.poisson(op.apply(truth) + 10).astype(np.float32)
    free = 1 << 40
    if not on_device:  # room for blocks of 48 px, not for the volumes
        monkeypatch.setattr(device_plan, "MIN_BLOCK", 48)
        free = int(block_bytes(op, op.image_shape[0], 48) / MEMORY_FRACTION) + 1
        plan = plan_on_device(op, op.image_shape[0], free, volumes=FISTA_VOLUMES)
        assert (plan.block, plan.volumes_on_device) == (48, False)
    dev = NumpyDevice("gpu", np, free=free)
    got = deblur_3d(stack, op, max_iter=10, rtol=0.0, grid_step=16, device=dev)
    ref = deblur_3d(stack, op, max_iter=10, rtol=0.0, grid_step=16, device="cpu")
    assert got.parameters["device"] == "gpu" and ref.parameters["device"] == "cpu"
    assert got.parameters["block"] == (96 if on_device else 48)
    assert isinstance(got.volume, np.ndarray) and got.volume.dtype == np.float32
    assert got.iterations == ref.iterations
    rel = np.linalg.norm(got.volume - ref.volume) / np.linalg.norm(ref.volume)
    assert rel <= got.iterations * 10 * U32, rel


def test_exchanged_tiles_on_the_device_path_are_the_whole_volume():
    """The tiles' blocks on the device path (NumPy standing in, every window moved there
    whole, or, with no room, its blocks copied one by one): the whole volume's
    Richardson-Lucy on the CPU, to float32 rounding (as on the CPU path)."""
    from napari_psfspace.core.volume.exchange3d import richardson_lucy_3d_exchange

    op = _operator(shape=(6, 96, 80))
    rng = np.random.default_rng(2)
    stack = rng.poisson(op.apply((rng.random(op.image_shape) < 0.01) * 300.0) + 5)
    whole = richardson_lucy_3d(stack, op, n_iter=4, block=16, device="cpu").volume
    for free in (1 << 40, 0):
        tiled = richardson_lucy_3d_exchange(stack, op, n_iter=4, tile=32, block=16,
                                            device=NumpyDevice("gpu", np, free=free))
        assert tiled.dtype == np.float32
        assert np.abs(tiled - whole).max() <= 1e-4 * whole.max()
