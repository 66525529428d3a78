"""Tolerances of float32 computations, derived from the arithmetic, not from one CPU.

A float32 result differs from the exact one by rounding, and how much depends on the
order of the sums (BLAS kernels, SIMD widths and FFT plans differ between CPUs). What
does not depend on the CPU is the classical bound on that error (Higham, *Accuracy and
Stability of Numerical Algorithms*, 2nd ed.):

* a sum of ``n`` products ``sum a_i b_i`` computed in any order is within
  ``gamma(n) sum |a_i b_i|`` of the exact one (Higham, eq. 3.5), with
  ``gamma(n) = n u / (1 - n u)`` and ``u`` the unit roundoff (half the machine epsilon);
* a radix-2 FFT of ``N`` points is within ``log2(N) eta / (1 - log2(N) eta)`` of the
  exact one in the 2-norm, relative to ``||x||_2 sqrt(N)`` (Higham, Thm 24.2), with
  ``eta = u + gamma(4) (sqrt(2) + u)`` for computed twiddle factors.

The tests bound the float32 error by these, with the sizes of what the test sums. The
inner products that compare two sides of a dot test are taken in float64 so that only
the operator's own rounding enters.
"""

from __future__ import annotations

import numpy as np

#: Unit roundoff of float32 (half its machine epsilon, 2**-24).
U32 = float(np.finfo(np.float32).eps) / 2
#: The same for float64 (the inner products that compare two sides).
U64 = float(np.finfo(np.float64).eps) / 2


def gamma(n: float, u: float = U32) -> float:
    """``n u / (1 - n u)``: the relative bound of ``n`` rounded operations in a row."""
    nu = float(n) * u
    if nu >= 1:
        raise ValueError(f"{n} operations exceed what precision {u:g} can bound.")
    return nu / (1 - nu)


def fft_relative_error(n_points: int, u: float = U32) -> float:
    """Bound on ``||fl(FFT x) - FFT x||_2 / ||FFT x||_2`` of an ``n_points`` FFT
    (Higham, Thm 24.2), for mixed radices counted as ``ceil(log2 N)`` passes."""
    passes = int(np.ceil(np.log2(max(int(n_points), 2))))
    eta = u + gamma(4, u) * (np.sqrt(2) + u)
    return passes * eta / (1 - passes * eta)


def abs_dot(a: np.ndarray, b: np.ndarray) -> float:
    """``sum |a_i b_i|`` in float64: the size of an inner product's terms."""
    return float(np.vdot(np.abs(np.asarray(a, np.float64)), np.abs(np.asarray(b, np.float64))))


def fft_convolution_error(kernel_l1, input_l2, *, n_points: int, kernel_size: int,
                          u: float = U32) -> float:
    """Bound on ``||fl(y) - y||_2`` for ``y = sum_i h_i * v_i`` computed by FFTs.

    The computation: ``v_i`` formed by a product (and a bilinear map: a few rounded
    operations), its FFT, the product with the kernel's spectrum (a direct DFT of the
    ``P x P`` patch: ``2 P`` rounded sums per coefficient, each term of modulus
    ``|h|``, so within ``gamma(4 P) ||h_i||_1``), the sum over ``i`` and one inverse FFT.
    With ``|K_i| <= ||h_i||_1`` and the FFT's norm ``sqrt(N)`` each error is at most
    its relative bound times ``||h_i||_1 ||v_i||_2``.

    Parameters
    ----------
    kernel_l1 : array_like of shape (I,)
        ``||h_i||_1`` (times ``max |alpha_i|`` for the adjoint, whose maps come last).
    input_l2 : array_like of shape (I,)
        ``||v_i||_2`` (``||alpha_i u||_2`` for the forward operator, ``||v||_2`` for the
        adjoint).
    n_points : int
        Points of the padded FFT (rows times columns).
    kernel_size : int
        ``P``.
    """
    k = np.asarray(kernel_l1, np.float64).reshape(-1)
    x = np.asarray(input_l2, np.float64).reshape(-1)
    rel = (gamma(6, u) + 2 * fft_relative_error(n_points, u) + gamma(4 * kernel_size, u)
           + gamma(len(k) + 4, u))
    return float(rel * np.sum(k * x))


def sum_error(values, u: float = U32) -> float:
    """Bound on the error of ``values.sum()`` in float32 after each value was rounded to
    float32: ``(u + gamma(d)) sum |x|`` with ``d`` the depth of NumPy's pairwise sum
    (blocks of 128 summed by 8 accumulators, then halved: ``16 + 3 + log2(n / 128)``)."""
    x = np.abs(np.asarray(values, np.float64)).ravel()
    depth = 19 + max(0, int(np.ceil(np.log2(max(x.size, 1) / 128))))
    return float((u + gamma(depth, u)) * x.sum())


def product_convolution_errors(op, u: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """Bounds on ``||fl32(H u) - H u||_2`` and ``||fl32(H^T v) - H^T v||_2`` of a
    :class:`~napari_psfspace.core.model.operator.ProductConvolution` run in float32
    (:func:`fft_convolution_error`, with ``v_i = alpha_i u`` forward and the maps last
    in the adjoint)."""
    maps = op.coefficient_maps(np.float64)
    l1 = np.abs(op.basis).sum(axis=(1, 2))
    fy, fx = op.fft_shape()
    kw = {"n_points": fy * fx, "kernel_size": op.psf_size}
    u = np.asarray(u, np.float64)
    err_hu = fft_convolution_error(l1, np.linalg.norm(maps * u, axis=(1, 2)), **kw)
    err_htv = fft_convolution_error(l1 * np.abs(maps).max(axis=(1, 2)),
                                    np.full(op.n_psf, np.linalg.norm(v)), **kw)
    return err_hu, err_htv


def product_convolution_3d_errors(op, u: np.ndarray, v: np.ndarray, prec: float = U32,
                                  *, fft_shape=None, n_blocks: int = 1
                                  ) -> tuple[float, float]:
    """Bounds on ``||fl(H u) - H u||_2`` and ``||fl(H^T v) - H^T v||_2`` of a
    :class:`~napari_psfspace.core.volume.operator3d.ProductConvolution3D` run at unit
    roundoff ``prec``.

    As :func:`fft_convolution_error`, but the kernels' spectra are full FFTs of the
    padded kernel: their error is at most ``fft_relative_error(N) ||K_i||_2`` in the
    2-norm, hence pointwise at most ``fft_relative_error(N) sqrt(N) ||h_i||_1``, a
    relative term on ``||h_i||_1 ||v_i||_2`` like the others.

    On ``n_blocks`` lateral blocks of FFT shape ``fft_shape``
    (:class:`~napari_psfspace.core.volume.blocks3d.BlockedOperator3D` with ``rtol=0``)
    each block's error obeys the same bound on its part of the products, and the blocks'
    errors add: at most ``sqrt(n_blocks)`` times the bound on the whole (Cauchy-Schwarz
    over a partition), plus the maps' own rounding to float32 (in ``gamma(6)``).
    """
    maps = op.coefficient_maps(np.float64)
    l1 = np.abs(op.basis).sum(axis=(1, 2, 3))
    n = int(np.prod(op.fft_shape(np.shape(u)[0]) if fft_shape is None else fft_shape))
    rel = (gamma(6, prec) + 2 * fft_relative_error(n, prec)
           + fft_relative_error(n, prec) * np.sqrt(n) + gamma(len(l1) + 4, prec))
    u = np.asarray(u, np.float64)
    err_hu = rel * float(np.sum(l1 * np.sqrt(((maps[:, None] * u[None]) ** 2).sum(
        axis=(1, 2, 3)))))
    err_htv = rel * float(np.sum(l1 * np.abs(maps).max(axis=(1, 2)))) * float(np.linalg.norm(v))
    scale = float(np.sqrt(n_blocks))
    return err_hu * scale, err_htv * scale
