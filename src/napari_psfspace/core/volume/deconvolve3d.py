"""3D deblurring with a space-varying 3D PSF: Richardson-Lucy with ``H`` and ``H^T``.

The multiplicative update for Poisson data ``y ~ P(H u + b)``:

.. math:: u_{k+1} = \\frac{u_k}{H^T 1} \\; H^T \\frac{y}{H u_k + b}

with the space-varying operator ``H`` of
:class:`~napari_psfspace.core.volume.operator3d.ProductConvolution3D` (``I + 1`` FFT
pairs each way) instead of one PSF. ``u`` stays non-negative; ``b`` is a constant
background (default: a low quantile of the stack). Everything runs in float32, on
lateral blocks (:mod:`~napari_psfspace.core.volume.blocks3d`) by default.
:func:`shift_invariant` gives the operator of one PSF (the centre's, or the average of
all beads), the baseline every space-varying result is compared with.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass

import numpy as np

from ..common.progress import Progress, run_with_progress
from ..common.threads import default_workers
from ..common.validate import check_int
from .blocks3d import BLOCK, RTOL, BlockedOperator3D
from .operator3d import ProductConvolution3D

#: Smallest denominator of the ratio ``y / (H u + b)`` (image units).
TINY = 1e-6
#: Voxels read to set the default background and the starting value.
STATS_VOXELS = 1 << 22


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
    n_kernels : float
        Kernels per block it ran on (mean over the blocks, by area; the model's
        ``I`` on the whole volume).
    """

    volume: np.ndarray
    iterations: int
    background: float
    n_kernels: float = 0.0


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


def stack_statistics(stack) -> tuple[float, float]:
    """``(background, mean)`` of a stack from a strided subsample of at most about
    ``STATS_VOXELS`` voxels: the default constant background (1st percentile) and the
    mean that starts the iteration. The same rule on every path (whole volume, blocks,
    tiles, dask), so that their results agree; a dask stack is read once, subsampled."""
    z, h, w = stack.shape
    step = max(1, int(np.ceil(np.sqrt(z * h * w / STATS_VOXELS))))
    sample = np.asarray(stack[:, ::step, ::step], dtype=np.float32)
    if not np.isfinite(sample).all():
        raise ValueError("`stack` contains NaN or infinite values")
    sample = np.clip(sample, 0, None)
    return float(np.percentile(sample, 1)), float(sample.mean())


def check_stack(stack, operator: ProductConvolution3D) -> None:
    """Raise a clear error unless ``stack`` is a volume of the operator's lateral
    shape."""
    if not isinstance(operator, ProductConvolution3D):
        raise TypeError(f"`operator` must be a ProductConvolution3D, got "
                        f"{type(operator).__name__}")
    shape = tuple(np.shape(stack))
    if len(shape) != 3 or shape[1:] != operator.shape[1:]:
        raise ValueError(f"`stack` must be a volume (Z, {operator.shape[1]}, "
                         f"{operator.shape[2]}), got shape {shape}")


def iter_richardson_lucy_3d(
    stack,
    operator: ProductConvolution3D,
    *,
    n_iter: int = 50,
    background: float | None = None,
    block: int | None = BLOCK,
    rtol: float = RTOL,
    workers: int | None = None,
    start: float | None = None,
) -> Generator[Progress, None, Deconvolved3D]:
    """Generator form of :func:`richardson_lucy_3d`: yields progress after every
    iteration (stop it there to cancel), returns the :class:`Deconvolved3D`."""
    check_stack(stack, operator)
    n_iter = check_int(n_iter, "n_iter", minimum=1)
    b0, mean = stack_statistics(stack)
    b = b0 if background is None else float(background)
    if not np.isfinite(b):
        raise ValueError(f"`background` must be finite, got {background!r}")
    # always a copy, clipped in place: a view of the user's array (a memmap of their
    # file) is never written to
    data = np.array(stack, dtype=np.float32, copy=True)
    np.clip(data, 0, None, out=data)
    if not np.isfinite(data.sum(dtype=np.float64)):
        raise ValueError("`stack` contains NaN or infinite values")
    yield Progress("setup", 0.0, "blocks and their kernels")
    op = operator if block is None else BlockedOperator3D(operator, block=block, rtol=rtol)
    workers = default_workers() if workers is None else workers  # FFT threads or blocks
    n_kernels = float(op.n_kernels) if block is not None else float(operator.n_psf)
    buf = np.ones_like(data)
    norm = op.adjoint(buf, workers=workers)
    np.maximum(norm, TINY * max(float(norm.max()), 1.0), out=norm)
    u = np.full_like(data, max(mean - b, TINY) if start is None else float(start))
    for k in range(n_iter):
        if block is None:
            buf = op.apply(u, workers=workers)
        else:
            op.apply(u, out=buf, workers=workers)
        buf += b
        np.maximum(buf, TINY, out=buf)
        np.divide(data, buf, out=buf)
        if block is None:
            u *= op.adjoint(buf, workers=workers)
        else:
            op.adjoint(buf, multiply_into=u, workers=workers)
        u /= norm
        yield Progress("iteration", (k + 1) / n_iter, f"iteration {k + 1} of {n_iter}")
    return Deconvolved3D(u, n_iter, b, n_kernels)


def richardson_lucy_3d(
    stack,
    operator: ProductConvolution3D,
    *,
    n_iter: int = 50,
    background: float | None = None,
    block: int | None = BLOCK,
    rtol: float = RTOL,
    workers: int | None = None,
    start: float | None = None,
    progress: Callable[[Progress], None] | None = None,
) -> Deconvolved3D:
    """Space-varying Richardson-Lucy deconvolution of a z-stack, in float32.

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
        Constant background ``b``; default the stack's 1st percentile
        (:func:`stack_statistics`).
    block : int or None
        Lateral block size of the operator
        (:class:`~napari_psfspace.core.volume.blocks3d.BlockedOperator3D`): memory
        bounded by four float32 volumes and the blocks' spectra, and each block on the
        few kernels its PSFs need. None: the whole volume on all the model's kernels.
    rtol : float
        With blocks, the largest relative error of a block's PSF against the model's
        (0: every block on all kernels, the exact operator).
    workers : int, optional
        Threads: over blocks, or the whole volume's FFTs; default the machine's cores.
    start : float, optional
        The constant value the iteration starts from; default the stack's mean less
        the background (a tile of a larger stack is given the stack's).
    progress : callable, optional
        Called after each iteration.

    Returns
    -------
    Deconvolved3D
    """
    return run_with_progress(iter_richardson_lucy_3d(
        stack, operator, n_iter=n_iter, background=background, block=block, rtol=rtol,
        workers=workers, start=start), progress)


__all__ = ["Deconvolved3D", "check_stack", "iter_richardson_lucy_3d", "richardson_lucy_3d",
           "shift_invariant", "stack_statistics"]
