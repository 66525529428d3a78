"""3D deblurring with a space-varying 3D PSF: Richardson-Lucy with ``H`` and ``H^T``.

The multiplicative update for Poisson data ``y ~ P(H u + b)``:

.. math:: u_{k+1} = \\frac{u_k}{H^T 1} \\; H^T \\frac{y}{H u_k + b}

with the space-varying operator ``H`` of
:class:`~napari_psfspace.core.volume.operator3d.ProductConvolution3D` (``I + 1`` FFT
pairs each way) instead of one PSF. ``u`` stays non-negative; ``b`` is a constant
background (default: a low quantile of the stack). Everything runs in float32.
:func:`shift_invariant` gives the operator of one PSF (the centre's, or the average of
all beads), the baseline every space-varying result is compared with.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass

import numpy as np

from ..common.progress import Progress, run_with_progress
from ..common.validate import check_int
from .operator3d import ProductConvolution3D

#: Smallest denominator of the ratio ``y / (H u + b)`` (image units).
TINY = 1e-6


@dataclass
class Deconvolved3D:
    """Result of :func:`richardson_lucy_3d`.

    Attributes
    ----------
    volume : ndarray of shape (Z, H, W), float32
        The deblurred volume (non-negative).
    iterations : int
    background : float
        The constant ``b`` used.
    n_kernels : int
        Kernels of the operator it ran on (fewer than the model's when compressed).
    """

    volume: np.ndarray
    iterations: int
    background: float
    n_kernels: int = 0


def shift_invariant(operator: ProductConvolution3D, y: float | None = None,
                    x: float | None = None) -> ProductConvolution3D:
    """The shift-invariant operator of one of ``operator``'s PSFs: at ``(y, x)``
    (default the field's centre), as a one-kernel operator with constant maps."""
    _, h, w = operator.shape
    y = (h - 1) / 2 if y is None else float(y)
    x = (w - 1) / 2 if x is None else float(x)
    kernel = operator.kernel_at(y, x)[None]
    return ProductConvolution3D(kernel, np.ones((1, 1, 1)), shape=operator.shape,
                                grid=(np.array([0.0]), np.array([0.0])),
                                plane=operator.plane, voxel_size=operator.voxel_size,
                                metadata={"shift_invariant_at": [y, x]})


def iter_richardson_lucy_3d(
    stack,
    operator: ProductConvolution3D,
    *,
    n_iter: int = 50,
    background: float | None = None,
    compression: float | None = None,
    workers: int | None = None,
) -> Generator[Progress, None, Deconvolved3D]:
    """Generator form of :func:`richardson_lucy_3d`: yields progress after every
    iteration (stop it there to cancel), returns the :class:`Deconvolved3D`."""
    if not isinstance(operator, ProductConvolution3D):
        raise TypeError(f"`operator` must be a ProductConvolution3D, got "
                        f"{type(operator).__name__}")
    n_iter = check_int(n_iter, "n_iter", minimum=1)
    y = np.asarray(stack)
    if y.ndim != 3 or y.shape[1:] != operator.shape[1:]:
        raise ValueError(f"`stack` must be a volume (Z, {operator.shape[1]}, "
                         f"{operator.shape[2]}), got shape {y.shape}")
    y = y.astype(np.float32)
    if not np.isfinite(y).all():
        raise ValueError("`stack` contains NaN or infinite values")
    b = float(np.percentile(y, 1)) if background is None else float(background)
    if not np.isfinite(b):
        raise ValueError(f"`background` must be finite, got {background!r}")
    data = np.clip(y, 0, None)
    if compression is not None:
        operator = operator.compressed(compression)
    norm = operator.adjoint(np.ones_like(data), workers=workers)
    norm = np.maximum(norm, TINY * max(float(norm.max()), 1.0))
    u = np.full_like(data, max(float(data.mean()) - b, TINY))
    for k in range(n_iter):
        model = operator.apply(u, workers=workers)
        model += b
        np.maximum(model, TINY, out=model)
        ratio = data / model
        u *= operator.adjoint(ratio, workers=workers)
        u /= norm
        yield Progress("iteration", (k + 1) / n_iter, f"iteration {k + 1} of {n_iter}")
    return Deconvolved3D(u, n_iter, b, operator.n_psf)


def richardson_lucy_3d(
    stack,
    operator: ProductConvolution3D,
    *,
    n_iter: int = 50,
    background: float | None = None,
    compression: float | None = None,
    workers: int | None = None,
    progress: Callable[[Progress], None] | None = None,
) -> Deconvolved3D:
    """Space-varying Richardson-Lucy deconvolution of a z-stack.

    Parameters
    ----------
    stack : array_like of shape (Z, H, W)
        The blurred volume, image units (counts).
    operator : ProductConvolution3D
        Its blur (:func:`~napari_psfspace.core.volume.estimate3d.estimate_operator_3d`;
        :func:`shift_invariant` for one PSF).
    n_iter : int
        Iterations.
    background : float, optional
        Constant background ``b``; default the stack's 1st percentile.
    compression : float, optional
        Run on the operator compressed to the fewest kernels within this relative
        error of its PSFs (:meth:`ProductConvolution3D.compressed`): an iteration costs
        ``2 (k + 1)`` FFTs for ``k`` kernels. None: the operator as it is.
    workers : int, optional
        FFT threads.
    progress : callable, optional
        Called after each iteration.

    Returns
    -------
    Deconvolved3D
    """
    return run_with_progress(iter_richardson_lucy_3d(
        stack, operator, n_iter=n_iter, background=background, compression=compression,
        workers=workers), progress)


__all__ = ["Deconvolved3D", "iter_richardson_lucy_3d", "richardson_lucy_3d",
           "shift_invariant"]
