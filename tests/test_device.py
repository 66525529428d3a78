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
        richardson_lucy_3d(np.ones(op.shape, np.float32), op, n_iter=1, device="gpu")


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
    stack = rng.poisson(op.apply(rng.random(op.shape) * 200) + 10).astype(np.float32)
    free = 1 << 40
    if not on_device:  # room for blocks of 48 px (the smallest tried here), not volumes
        monkeypatch.setattr(device_plan, "MIN_BLOCK", 48)
        free = int(block_bytes(op, op.shape[0], 48) / MEMORY_FRACTION) + 1
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
