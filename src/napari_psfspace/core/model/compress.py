"""Fewer kernels for the same operator: the PSF field's own rank, to a stated error.

A product-convolution operator ``H u = sum_i h_i * (alpha_i . u)`` costs ``2 (I + 1)``
FFTs per application of ``H`` and ``H^T``. An operator identified from a family carries
the family's ``I`` kernels, although one image's PSFs vary over a smaller space (a
field near focus keeps almost all its energy on half the family's directions,
``bench/bench_deblur_tol.py``). :func:`compress_operator` finds them.

The PSF at ``x`` is ``alpha(x)^T B`` (``B``: the basis as ``I`` rows of ``P^2``
pixels), and ``alpha(x)`` is linear in the stored coefficients (bilinear between grid
nodes, or the full-resolution maps). With ``M`` the PSFs at the stored coefficients
(one row per node or pixel) and ``M = U S V^T``, the operator with basis ``V_k^T`` and
coefficients ``(B V_k)^T alpha`` has the PSF ``alpha(x)^T B V_k V_k^T``: the orthogonal
projection of the true PSF on the first ``k`` directions, at every position (the
projection is linear, so it commutes with the interpolation). Its error at ``x`` is at
most the weighted mean of the errors at the rows it interpolates (bilinear weights are
non-negative and sum to one), each of which ``rtol`` bounds relative to its row.
"""

from __future__ import annotations

import numpy as np

from .operator import ProductConvolution

#: Rows of ``M`` at most in the decomposition (full-resolution maps are subsampled).
MAX_ROWS = 65536


def compressed_field(basis: np.ndarray, coefficients: np.ndarray, rtol: float
                     ) -> tuple[np.ndarray, np.ndarray, int, float] | None:
    """The fewest orthonormal kernels whose field stays within ``rtol`` of a field's own
    (the module's notes), for kernels of any shape.

    Parameters
    ----------
    basis : ndarray of shape (I, ...)
        The kernels (2D or 3D).
    coefficients : ndarray of shape (I, ...)
        Their coefficients at the stored positions (grid nodes or pixels).
    rtol : float
        Largest relative l2 error of the kernel at any stored position.

    Returns
    -------
    (new_basis (k, ...), new_coefficients (k, ...), k, error) or None
        None when no kernel can be dropped.
    """
    if not (np.isfinite(rtol) and rtol >= 0):
        raise ValueError(f"`rtol` must be a finite number >= 0, got {rtol!r}")
    basis = np.asarray(basis, np.float64)
    n, shape = basis.shape[0], basis.shape[1:]
    b = basis.reshape(n, -1)  # (I, D)
    coef = np.asarray(coefficients, np.float64).reshape(n, -1)  # (I, rows)
    if coef.shape[1] > MAX_ROWS:
        coef = coef[:, :: int(np.ceil(coef.shape[1] / MAX_ROWS))]
    # M = coef^T B = coef^T R^T Q^T with B^T = Q R: the SVD of the small (rows, I) part
    q, r = np.linalg.qr(b.T)  # (D, I), (I, I)
    u, s, wt = np.linalg.svd(coef.T @ r.T, full_matrices=False)
    us = u * s  # rows of M in the orthonormal directions V = Q W
    total = np.einsum("ij,ij->i", us, us)
    kept = np.cumsum(us ** 2, axis=1)  # energy of each row on the first k directions
    scale = np.maximum(total, 1e-300)
    k = n
    for j in range(1, n + 1):
        err = np.sqrt(np.clip(total - kept[:, j - 1], 0, None) / scale)
        if float(err.max()) <= rtol or s[j - 1] == 0:
            k = j
            break
    if k >= n:
        return None
    err = float(np.sqrt(np.clip(total - kept[:, k - 1], 0, None) / scale).max())
    v = q @ wt.T[:, :k]  # (D, k), orthonormal
    new_basis = v.T.reshape(k, *shape)
    mix = b @ v  # (I, k): alpha' = mix^T alpha
    new_coef = np.tensordot(mix.T, np.asarray(coefficients, np.float64), axes=1)
    return new_basis, new_coef, k, err


def compress_operator(operator: ProductConvolution, rtol: float) -> ProductConvolution:
    """The operator on the fewest kernels whose PSFs stay within ``rtol`` of its own.

    Parameters
    ----------
    operator : ProductConvolution
        ``I`` kernels of ``P x P`` pixels.
    rtol : float
        Largest relative l2 error of the PSF at any stored position (grid node or, for
        full-resolution maps, pixel): ``||psf - psf_k|| <= rtol ||psf||``. 0 keeps
        every direction the field uses (exact to rounding).

    Returns
    -------
    ProductConvolution
        ``k <= I`` kernels (orthonormal), the same grid, shape and metadata, plus
        ``metadata["compressed"] = {"from": I, "to": k, "rtol": rtol, "error": e}``
        with ``e`` the largest relative error reached. The operator itself when no
        kernel can be dropped.
    """
    found = compressed_field(operator.basis, operator.coefficients, rtol)
    if found is None:
        return operator
    new_basis, new_coef, k, err = found
    n = operator.basis.shape[0]
    meta = dict(operator.metadata or {})
    meta["compressed"] = {"from": int(n), "to": int(k), "rtol": float(rtol), "error": err}
    if operator.is_full_resolution:
        return ProductConvolution(new_basis, new_coef, metadata=meta)
    return ProductConvolution(new_basis, new_coef, shape=operator.image_shape,
                              grid=operator.grid, metadata=meta)
