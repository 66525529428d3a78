"""Timing benchmarks under asv (airspeed velocity), as scikit-image and napari time theirs.

    asv run --quick --python=same        # once each, in the current environment
    asv continuous main HEAD             # a change against main, in fresh environments

What is timed: the estimate on a 2304 x 2304 bead image (``bench/bench_speed.py``'s
case), the product-convolution operator and its adjoint on 2048 x 2048 (``bench_apply``),
Richardson-Lucy 3D on a space-varying volume (``bench_rl3d_speed``), and the sparse +
smooth deblurring (``bench_deblur_speed``). Each class's sizes are class attributes, so
that ``tests/test_asv_benchmarks.py`` runs every benchmark on small ones. The accuracy
studies stay scripts under ``bench/`` (``bench/run.py``).
"""

import numpy as np


def _gaussian_basis(n_psf: int, size: int) -> np.ndarray:
    """``n_psf`` Gaussian PSFs of widening sd on ``size x size`` (odd), each of sum 1."""
    c = size // 2
    yy, xx = np.mgrid[-c:c + 1, -c:c + 1]
    basis = np.array([np.exp(-(yy**2 + xx**2) / (2.0 * (1.5 + 0.4 * i) ** 2))
                      for i in range(n_psf)])
    return basis / basis.sum(axis=(1, 2), keepdims=True)


def _operator(shape, n_psf: int, psf: int):
    from napari_psfspace.core.model.operator import ProductConvolution

    rng = np.random.default_rng(0)
    grid = (np.linspace(0, shape[0] - 1, 5), np.linspace(0, shape[1] - 1, 5))
    coef = 0.5 + rng.random((n_psf, 5, 5))
    return ProductConvolution(_gaussian_basis(n_psf, psf), coef, shape=shape, grid=grid)


class EstimateOperator:
    """``estimate_operator`` on a simulated bead image (2 cores: the project's target)."""

    shape = (2304, 2304)
    n_beads = 400
    timeout = 600

    def setup(self):
        from napari_psfspace.core.simulation import simulate_beads

        self.image, truth = simulate_beads(self.shape, self.n_beads, seed=0)
        self.radius = truth.psf_radius

    def time_estimate_operator(self):
        from napari_psfspace.core.model.estimate import estimate_operator

        estimate_operator(self.image, psf_radius=self.radius)

    def peakmem_estimate_operator(self):
        self.time_estimate_operator()


class ApplyOperator:
    """``ProductConvolution.apply`` and ``adjoint`` (kernel spectra and maps cached by a
    first call, as in an iterative deblurring)."""

    shape = (2048, 2048)
    n_psf = 8
    psf = 41

    def setup(self):
        self.op = _operator(self.shape, self.n_psf, self.psf)
        self.u = np.random.default_rng(1).random(self.shape, dtype=np.float32)
        self.op.adjoint(self.op.apply(self.u))

    def time_apply(self):
        self.op.apply(self.u)

    def time_adjoint(self):
        self.op.adjoint(self.u)


class RichardsonLucy3D:
    """Accelerated Richardson-Lucy on a space-varying volume, on the CPU."""

    shape = (32, 512, 512)
    kernel = (31, 21, 21)
    n_iter = 4
    timeout = 600

    def setup(self):
        from napari_psfspace.core.volume.operator3d import ProductConvolution3D

        rng = np.random.default_rng(0)
        basis = rng.random((4, *self.kernel))
        basis /= basis.sum(axis=(1, 2, 3), keepdims=True)
        grid = (np.linspace(0, self.shape[1] - 1, 4), np.linspace(0, self.shape[2] - 1, 4))
        self.op = ProductConvolution3D(basis, 0.5 + rng.random((4, 4, 4)), shape=self.shape,
                                       grid=grid, plane=self.kernel[0] // 2)
        self.stack = rng.poisson(50, self.shape).astype(np.float32)

    def time_richardson_lucy_3d(self):
        from napari_psfspace.core.volume.deconvolve3d import richardson_lucy_3d

        richardson_lucy_3d(self.stack, self.op, n_iter=self.n_iter, accelerate=True)


class Deblur:
    """The sparse + smooth deblurring (a fixed number of iterations) of points on a smooth
    background."""

    shape = (1024, 1024)
    n_psf = 8
    psf = 41
    max_iter = 50
    timeout = 600

    def setup(self):
        rng = np.random.default_rng(2)
        self.op = _operator(self.shape, self.n_psf, self.psf)
        truth = np.zeros(self.shape, np.float32)
        idx = rng.integers(0, self.shape[0], (200, 2))
        truth[idx[:, 0], idx[:, 1]] = 1000.0
        yy, xx = np.mgrid[:self.shape[0], :self.shape[1]] / self.shape[0]
        truth += (50.0 + 20.0 * np.sin(3 * yy) * np.cos(2 * xx)).astype(np.float32)
        self.image = rng.poisson(self.op.apply(truth)).astype(np.float32)

    def time_deblur(self):
        from napari_psfspace.core.restore import deblur

        deblur(self.image, self.op, max_iter=self.max_iter)
