"""The GPU path (CuPy), where CuPy sees a device: the same results as the CPU's to float32
rounding. Skipped elsewhere, with the reason (CI has no GPU)."""

import numpy as np
import pytest

from napari_psfspace.core.common.device import array_module, gpu_status

_OK, _WHY = gpu_status()
pytestmark = pytest.mark.skipif(not _OK, reason=f"no GPU path here: {_WHY}")


def _operator(shape=(16, 256, 224), kernel=(9, 21, 21), n=4, seed=0):
    from napari_psfspace.core.volume.operator3d import ProductConvolution3D

    rng = np.random.default_rng(seed)
    basis = rng.random((n, *kernel))
    basis /= basis.sum(axis=(1, 2, 3), keepdims=True)
    gy, gx = np.linspace(0, shape[1] - 1, 5), np.linspace(0, shape[2] - 1, 4)
    return ProductConvolution3D(basis, 0.5 + rng.random((n, 5, 4)), shape=shape,
                                grid=(gy, gx), plane=n)


def test_auto_is_the_gpu():
    assert array_module("auto").gpu


def test_the_blocked_operator_on_the_gpu_is_the_cpus():
    from napari_psfspace.core.volume.blocks3d import BlockedOperator3D

    op = _operator()
    rng = np.random.default_rng(1)
    u, v = rng.random((2, *op.shape)).astype(np.float32)
    am = array_module("gpu")
    gpu = BlockedOperator3D(op, block=256, rtol=0.0, device=am)
    cpu = BlockedOperator3D(op, block=256, rtol=0.0)
    for a, b in ((gpu.apply(am.asarray(u)), cpu.apply(u)),
                 (gpu.adjoint(am.asarray(v)), cpu.adjoint(v))):
        a = am.to_host(a)
        assert np.linalg.norm(a - b) <= 1e-5 * np.linalg.norm(b)
    # host volumes through the device's blocks (tiles): the same
    assert np.linalg.norm(gpu.apply(u) - cpu.apply(u)) <= 1e-5 * np.linalg.norm(cpu.apply(u))


@pytest.mark.parametrize("accelerate", [False, True])
def test_ten_iterations_on_the_gpu_are_the_cpus(accelerate):
    from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d

    op = _operator()
    rng = np.random.default_rng(2)
    stack = rng.poisson(op.apply(rng.random(op.shape) * 100) + 10).astype(np.float32)
    gpu = richardson_lucy_3d(stack, op, n_iter=10, device="gpu", accelerate=accelerate)
    cpu = richardson_lucy_3d(stack, op, n_iter=10, device="cpu", accelerate=accelerate)
    assert gpu.device == "gpu" and isinstance(gpu.volume, np.ndarray)
    rel = np.linalg.norm(gpu.volume - cpu.volume) / np.linalg.norm(cpu.volume)
    assert rel <= 1e-5, rel  # the bound: float32 rounding
