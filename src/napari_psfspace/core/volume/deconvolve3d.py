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

import time
from collections.abc import Generator
from dataclasses import dataclass, field

import numpy as np

from ..common.device import array_module
from ..common.heap import kept_heap
from ..common.progress import Progress
from ..common.threads import default_workers
from ..common.twins import drained
from ..common.validate import (
    as_stack,
    check_background,
    check_finite,
    check_int,
    check_memory,
    check_signal,
)
from .blocks3d import BLOCK, RTOL, BlockedOperator3D
from .device_plan import plan_on_device
from .operator3d import ProductConvolution3D

#: Smallest denominator of the ratio ``y / (H u + b)`` (image units).
TINY = 1e-6
#: The least largest value of a stack the iterations take: a thousand times their floor,
#: so that the floor is below the data's noise (a stack scaled far below is refused).
SMALLEST_TOP = 1e3 * TINY
#: Voxels read to set the default background and the starting value.
STATS_VOXELS = 1 << 22
#: The stopping rule's default: an iteration that improves the data fit (Poisson
#: deviance) by less than this fraction of itself ends the iteration (``stop``; its
#: effect on the result: bench/bench_deblur3d_panel.py).
STOP_FIT = 3e-3
#: Largest extrapolation factor of the accelerated iteration (Biggs and Andrews 1997,
#: who bound it below 1).
ALPHA_MAX = 0.95
#: Iterations always run before the stopping rule is read.
MIN_ITERATIONS = 5
#: Seconds of the products with the maps and spectra per second of an iteration's FFT
#: pairs, for the time estimate.
OVERHEAD = 1.6
#: Passes over a volume an iteration makes besides its blocks (the ratio to the data,
#: the update, the copies), for the time estimate; more with the acceleration's
#: extrapolation.
PASSES = 8
PASSES_ACCELERATED = 16


def estimate_seconds(op: BlockedOperator3D, volume: np.ndarray, n_iter: int,
                     workers: int, *, accelerate: bool = False) -> float:
    """Seconds ``n_iter`` blocked Richardson-Lucy iterations and their setup should take
    here, from two timings (each the median of three): one FFT pair of the blocks'
    padded shape on one thread (as each block runs), counted
    (:meth:`BlockedOperator3D.fft_pairs` an iteration, half an iteration for the
    setup's ``H^T 1``; the blocks shared among ``workers`` threads) times
    :data:`OVERHEAD` for the products around them; and one pass over ``volume`` (a
    float32 array of the stack's shape, overwritten), counted :data:`PASSES` an
    iteration (:data:`PASSES_ACCELERATED` with the acceleration)."""
    am = op.am
    shape = op.fft_shape(volume.shape[0])
    x = am.xp.zeros(shape, np.float32)
    vx = np if isinstance(volume, np.ndarray) else am.xp

    def median_time(fn) -> float:
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            fn()
            am.synchronize()
            times.append(time.perf_counter() - t0)
        return float(np.median(times))

    pair = median_time(lambda: am.irfftn(am.rfftn(x, workers=1), s=shape, workers=1))
    one_pass = median_time(lambda: vx.multiply(volume, 1.0, out=volume))
    threads = 1 if am.gpu else max(1, min(int(workers), len(op.blocks)))
    passes = PASSES_ACCELERATED if accelerate else PASSES
    per_iteration = OVERHEAD * pair * op.fft_pairs() / threads + passes * one_pass
    return float(per_iteration * (n_iter + 0.5))


def _duration(seconds: float) -> str:
    seconds = max(0.0, float(seconds))
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min"


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
    changes : list of float
        Relative change of each iteration, ``||u_k - u_{k-1}|| / ||u_k||`` (on a
        strided subsample of about ``4 STATS_VOXELS`` voxels).
    stopped : bool
        True when the stopping rule ended the iteration before ``n_iter``.
    estimate_s : float or None
        The time the run was expected to take at its start (seconds; blocks only).
    device : str
        Where it ran: "cpu" or "gpu".
    block : int or None
        The lateral block size it ran on (None: the whole volume at once).
    deviances : list of float
        The data fit of the iterates ``u_0, u_1, ...`` (Poisson deviance per voxel of
        ``H u + b`` against the stack, on the same subsample): what the stopping rule
        reads.
    """

    volume: np.ndarray
    iterations: int
    background: float
    n_kernels: float = 0.0
    changes: list = field(default_factory=list)
    stopped: bool = False
    estimate_s: float | None = None
    deviances: list = field(default_factory=list)
    device: str = "cpu"
    block: int | None = None


def shift_invariant(operator: ProductConvolution3D, y: float | None = None,
                    x: float | None = None) -> ProductConvolution3D:
    """The shift-invariant operator of one of ``operator``'s PSFs: at ``(y, x)``
    (default the field's centre), as a one-kernel operator with constant maps."""
    _, h, w = operator.image_shape
    y = (h - 1) / 2 if y is None else float(y)
    x = (w - 1) / 2 if x is None else float(x)
    kernel = operator.kernel_at(y, x)[None]
    return ProductConvolution3D(kernel, np.ones((1, 1, 1)), shape=operator.image_shape,
                                grid=(np.array([0.0]), np.array([0.0])),
                                plane=operator.plane, voxel_size=operator.voxel_size,
                                metadata={"shift_invariant_at": [y, x]})


def stack_statistics(stack, background: float | None = None) -> tuple[float, float]:
    """``(background, mean)`` of a stack from a strided subsample of at most about
    ``STATS_VOXELS`` voxels: the constant background (``background`` where given, else
    the 1st percentile) and the mean that starts the iteration. The same rule on every
    path (whole volume, blocks, tiles, dask), so that their results agree; a dask stack
    is read once, subsampled.

    Raises
    ------
    ValueError
        NaN or infinite values; a stack with no positive value or one value everywhere
        (the whole of an in-memory stack is checked where its sample fails); a
        ``background`` that is not finite or not below the stack's largest value."""
    z, h, w = stack.shape
    step = max(1, int(np.ceil(np.sqrt(z * h * w / STATS_VOXELS))))
    sample = np.asarray(stack[:, ::step, ::step], dtype=np.float32)
    check_finite(sample, "stack")  # a lazy stack's sample; one in memory is checked whole
    top = float(sample.max())
    if not (top > 0 and float(sample.min()) < top):  # sparse light the sample missed?
        whole = stack if isinstance(stack, np.ndarray) else sample
        check_signal(whole, "stack")
        top = float(np.max(whole))
    if top < SMALLEST_TOP:
        raise ValueError(f"`stack`: its largest value {top:.3g} is too small for the "
                         f"iterations' floor {TINY:g} (at least {SMALLEST_TOP:g}): scale "
                         "it, e.g. to camera counts")
    sample = np.clip(sample, 0, None)
    b = (float(np.percentile(sample, 1)) if background is None else
         check_background(background, top))
    return b, float(sample.mean())


def check_stack(stack, operator: ProductConvolution3D, *, copies: float = 0.0) -> None:
    """Raise a clear error unless ``stack`` is a volume of the operator's lateral
    shape (the stacks' validator), and, where ``copies`` is given, unless that many
    float32 volumes of its size fit in memory."""
    if not isinstance(operator, ProductConvolution3D):
        raise TypeError(f"`operator` must be a ProductConvolution3D, got "
                        f"{type(operator).__name__}")
    as_stack(stack, lateral=operator.image_shape[1:], copies=copies)


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
    stop: float | None = None,
    accelerate: bool = False,
    device: str = "auto",
) -> Generator[Progress, None, Deconvolved3D]:
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
    accelerate : bool
        Biggs and Andrews' vector extrapolation (Appl. Opt. 36, 1997): each step starts
        from ``x_k + a (x_k - x_{k-1})``, ``a`` from the last two steps' agreement; the
        same fixed point in fewer iterations, at four more volumes of memory.
    stop : float, optional
        The stopping rule: end when an iteration improves the fit to the data by less
        than this, relative: the Poisson deviance of ``H u_k + b`` against the stack
        lowered by less than ``stop`` times itself (after at least
        :data:`MIN_ITERATIONS`; ``n_iter`` is then the most). The iterate returned is
        ``u_k``. The estimate itself keeps moving long after (its change per iteration
        is in ``changes``). None (default): ``n_iter`` iterations. :data:`STOP_FIT` is
        the panel's.
    device : {"auto", "cpu", "gpu"}
        Where the iteration runs (:mod:`~napari_psfspace.core.common.device`): "auto" is
        the GPU when CuPy imports and sees a device, else the CPU. On the GPU the blocks
        are sized from the device's free memory (``block`` is then not used:
        :mod:`~napari_psfspace.core.volume.device_plan`). The result is a NumPy array.

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    Deconvolved3D
    """
    n_iter, am = _checked(stack, operator, n_iter, stop, accelerate, device)
    b, mean = stack_statistics(stack, background)  # its refusals before any progress
    yield Progress("setup", 0.0, f"background {b:.4g}, mean {mean:.4g}")
    with kept_heap():  # the blocks' temporaries reuse the heap (common.heap)
        return (yield from _run(stack, operator, b, mean, am, n_iter=n_iter, start=start,
                                stop=stop, accelerate=accelerate, block=block, rtol=rtol,
                                workers=workers))


def _run(stack, operator, b, mean, am, *, n_iter, start, stop, accelerate, block, rtol,
         workers):
    """The iterations of :func:`iter_richardson_lucy_3d` on checked arguments."""
    v = _Volumes()  # the volumes, held once: each freed as soon as it is no longer needed
    v.data = yield from _float32_copy(stack)
    yield Progress("setup", 0.0, "blocks and their kernels")
    op, block, xp = _blocked(operator, v, am, block, rtol, accelerate)
    workers = default_workers() if workers is None else workers  # FFT threads or blocks
    n_kernels = float(op.n_kernels) if block is not None else float(operator.n_psf)
    estimate = yield from _normalisation(op, v, xp, n_iter, workers, accelerate, am,
                                         blocked=block is not None)
    yield Progress("setup", 0.0, "the starting estimate")
    v.u = xp.full_like(v.data, max(mean - b, TINY) if start is None else float(start))
    changes, deviances = yield from _iterations(op, v, b, xp, n_iter=n_iter, stop=stop,
                                                accelerate=accelerate, workers=workers,
                                                blocked=block is not None)
    u = v.u
    del v
    stopped = len(changes) < n_iter
    volume = am.to_host(u) if xp is not np else u
    del u
    if isinstance(op, BlockedOperator3D) and am.gpu:
        op.release()  # its spectra and plans go back to the device
    return Deconvolved3D(volume, len(changes), b, n_kernels, changes, stopped, estimate,
                         deviances, am.name, block)


class _Volumes:
    """The iteration's volumes: the data, a buffer (``H u`` or the ratio), ``H^T 1`` and
    the iterate, referenced from here alone so that each is freed when dropped."""

    data = buf = norm = u = None


def _checked(stack, operator, n_iter, stop, accelerate, device):
    """``n_iter`` and the array module, checked, and the memory the volumes need on the
    CPU; one clear line for a bad value before any work."""
    check_stack(stack, operator)
    n_iter = check_int(n_iter, "n_iter", minimum=1)
    if stop is not None and not (np.isfinite(stop) and stop >= 0):
        raise ValueError(f"`stop` must be a finite number >= 0 or None, got {stop!r}")
    am = array_module(device)  # "gpu" without CuPy or a device: one line, no work done
    if not am.gpu:  # the data, H u or the ratio, H^T 1 and the iterate (+ 4 accelerated)
        volumes = 8 if accelerate else 4
        z, h, w = np.shape(stack)
        check_memory(volumes * 4.0 * z * h * w,
                     f"Richardson-Lucy in memory on {z} x {h} x {w} voxels ({volumes} "
                     "float32 volumes)",
                     hint="Deblur it in tiles from a memory budget: psfspace deblur3d "
                          "--memory 4GB, or richardson_lucy_3d_exchange.")
    return n_iter, am


def _float32_copy(stack) -> Generator[Progress, None, np.ndarray]:
    """The stack as a float32 copy clipped at 0 in place: a view of the user's array (a
    memmap of their file) is never written to."""
    data = np.array(stack, dtype=np.float32, copy=True)
    yield Progress("setup", 0.0, "a float32 copy of the stack")
    np.clip(data, 0, None, out=data)
    if not np.isfinite(data.sum(dtype=np.float64)):
        raise ValueError("`stack` contains NaN or infinite values")
    return data


def _blocked(operator, v: _Volumes, am, block, rtol, accelerate):
    """The operator in blocks (on a GPU, blocks as large as the device's memory allows,
    :mod:`.device_plan`, with the data moved there where the volumes fit), the block
    size and the volumes' array module."""
    xp = np
    if am.gpu:
        plan = plan_on_device(operator, v.data.shape[0], am.free_bytes(),
                              accelerate=accelerate)
        block = plan.block
        if plan.volumes_on_device:
            xp = am.xp
            v.data = am.asarray(v.data)
        return BlockedOperator3D(operator, block=block, rtol=rtol, device=am), block, xp
    op = operator if block is None else BlockedOperator3D(operator, block=block, rtol=rtol)
    return op, block, xp


def _normalisation(op, v: _Volumes, xp, n_iter, workers, accelerate, am, *, blocked):
    """``H^T 1`` (floored at a tiny fraction of its top) into ``v.norm``, the buffer into
    ``v.buf``; with blocks, the estimated time of the run first."""
    estimate = None
    v.buf = xp.empty_like(v.data)
    v.buf.fill(1.0)
    if blocked:
        yield Progress("setup", 0.0, "timing one FFT of a block")
        estimate = estimate_seconds(op, v.buf, n_iter, workers, accelerate=accelerate)
        yield Progress("estimate", 0.0, f"about {_duration(estimate)} for {n_iter} "
                                        f"iterations at most"
                                        + (" on the GPU" if am.gpu else ""))
        v.buf.fill(1.0)
    if not blocked:
        v.norm = op.adjoint(v.buf, workers=workers)
    else:
        v.norm = yield from _waves(op.iter_adjoint(v.buf, workers=workers), "setup", 0.0,
                                   0.0, "H^T 1")
    xp.maximum(v.norm, TINY * max(float(v.norm.max()), 1.0), out=v.norm)
    return estimate


def _iterations(op, v: _Volumes, b, xp, *, n_iter, stop, accelerate, workers, blocked):
    """The Richardson-Lucy iterations on ``v.u`` (Biggs-Andrews accelerated on request),
    to ``n_iter`` or the stopping rule; the change of each iteration and the data fit
    of each iterate (Poisson deviance per voxel), both read on a strided subsample (a
    sixteenth of a 1024 x 1024 stack: no fifth volume in memory). ``v.buf``, ``v.norm``
    and ``v.data`` are dropped at the end."""
    u, data = v.u, v.data
    z, h, w = u.shape
    step = max(1, int(np.ceil(np.sqrt(z * h * w / (4 * STATS_VOXELS)))))
    prev = xp.empty_like(u[:, ::step, ::step])
    changes: list[float] = []
    fit = _DevianceOnSample(data[:, ::step, ::step], xp)
    deviances: list[float] = []
    if accelerate:  # Biggs-Andrews: x_{k-1}, the last two steps g, the prediction y
        made = []
        for _ in range(4):
            made.append(xp.zeros_like(u))
            yield Progress("setup", 0.0, "the acceleration's volumes")
        x_prev, g1, g2, g_new = made
        del made
    t_iter = time.perf_counter()
    for k in range(n_iter):
        xp.copyto(prev, u[:, ::step, ::step])
        if accelerate:
            _predict(u, x_prev, g1, g2, g_new, k, xp)
        left = ""
        if k:
            per = (time.perf_counter() - t_iter) / k
            left = f", {_duration(per * (n_iter - k))} left at most"
        where = (k / n_iter, 1 / n_iter, f"iteration {k + 1} of {n_iter}{left}")
        if not blocked:
            v.buf = op.apply(u, workers=workers)
        else:
            yield Progress("iteration", where[0], where[2])  # after the extrapolation
            yield from _waves(op.iter_apply(u, out=v.buf, workers=workers), "iteration",
                              where[0], where[1] / 2, where[2])
        v.buf += b
        xp.maximum(v.buf, TINY, out=v.buf)
        deviances.append(fit(v.buf[:, ::step, ::step]))
        if (stop is not None and k >= MIN_ITERATIONS
                and deviances[-2] - deviances[-1] < stop * deviances[-1]):
            if accelerate:  # the iterate, not its extrapolation
                xp.copyto(u, x_prev)
            break  # u_k fits the data as well as u_{k-1}, to ``stop``: it is the result
        xp.divide(data, v.buf, out=v.buf)
        if not blocked:
            u *= op.adjoint(v.buf, workers=workers)
        else:
            yield Progress("iteration", where[0] + where[1] / 2, where[2])
            yield from _waves(op.iter_adjoint(v.buf, multiply_into=u, workers=workers),
                              "iteration", where[0] + where[1] / 2, where[1] / 2, where[2])
        u /= v.norm
        # light is never negative: the blocks' compressed kernels and the FFTs' rounding
        # can leave a voxel a little below zero, which the next update would amplify
        xp.maximum(u, 0, out=u)
        if accelerate:  # this step's change from its prediction
            xp.subtract(u, g_new, out=g_new)
            g1, g2, g_new = g_new, g1, g2
        now = u[:, ::step, ::step]
        prev -= now
        changes.append(float(xp.linalg.norm(prev) / max(xp.linalg.norm(now), TINY)))
        yield Progress("iteration", (k + 1) / n_iter,
                       f"iteration {k + 1} of {n_iter}, change {changes[-1]:.2g}")
    v.buf = v.norm = v.data = None
    return changes, deviances


class _DevianceOnSample:
    """The Poisson deviance per voxel, ``2 mean(y log(y / mu) - (y - mu))``, of the
    blurred estimate ``mu = H u + b`` against the data ``y`` on a fixed subsample (the
    terms of ``y`` alone computed once), in the array module ``xp`` of the volumes."""

    def __init__(self, y, xp=np) -> None:
        self.xp = xp
        self.y = xp.ascontiguousarray(y, dtype=np.float64)
        pos = self.y > 0
        self.const = float(xp.sum(self.y[pos] * xp.log(self.y[pos])) - self.y.sum())
        self.n = max(self.y.size, 1)

    def __call__(self, mu) -> float:
        xp = self.xp
        m = xp.asarray(mu, dtype=np.float64)
        return 2.0 * (self.const - float(xp.sum(self.y * xp.log(m))) + float(m.sum())) / self.n


def _predict(u, x_prev, g1, g2, y, k: int, xp=np) -> float:
    """Biggs-Andrews vector extrapolation before Richardson-Lucy step ``k`` (in place):
    ``u`` (the estimate ``x_k``) becomes the prediction ``x_k + a (x_k - x_{k-1})``,
    clipped at 0, with ``a = <g_{k-1}, g_{k-2}> / <g_{k-2}, g_{k-2}>`` in
    ``[0, ALPHA_MAX]`` (0 for the first two steps), the ``g`` being the steps' changes
    from their predictions; ``x_prev`` becomes ``x_k`` and ``y`` the prediction.
    Returns ``a``."""
    alpha = 0.0
    if k >= 2:
        den = float(xp.dot(g2.ravel(), g2.ravel()))
        if den > 0:
            alpha = float(xp.clip(xp.dot(g1.ravel(), g2.ravel()) / den, 0.0, ALPHA_MAX))
    if k >= 1 and alpha > 0:
        xp.subtract(u, x_prev, out=y)  # x_k - x_{k-1}, in y's buffer for a moment
        xp.copyto(x_prev, u)
        y *= alpha
        u += y
        xp.maximum(u, 0, out=u)
    else:
        xp.copyto(x_prev, u)
    xp.copyto(y, u)
    return alpha


def _waves(gen, stage: str, start: float, span: float, message: str):
    """Progress records of a blocked ``apply`` or ``adjoint``: one a wave of blocks,
    its fraction placed within ``start .. start + span`` of the whole run; returns the
    operator's result."""
    while True:
        try:
            done = next(gen)
        except StopIteration as stop:
            return stop.value
        yield Progress(stage, start + span * done, message)


richardson_lucy_3d = drained(iter_richardson_lucy_3d, "richardson_lucy_3d")


__all__ = ["MIN_ITERATIONS", "STOP_FIT", "Deconvolved3D", "check_stack",
           "estimate_seconds", "iter_richardson_lucy_3d", "richardson_lucy_3d",
           "shift_invariant", "stack_statistics"]
