"""Sparse + smooth 3D deblurring with a space-varying 3D PSF (the paper's model in 3D).

The 2D method (:mod:`~napari_psfspace.core.restore.deconvolve`) on a z-stack:

.. math:: \\min_{u_1 \\ge 0,\\, w \\ge 0} \\tfrac12 \\|H (u_1 + U w) - y\\|^2
          + \\sum_x \\gamma_1 |u_1(x)| + \\gamma_2' \\|L w\\|^2

``u_1`` holds the point-like part (voxels), ``U w`` the smooth part (background,
out-of-focus haze): nodes every ``grid_step`` pixels on each plane (bilinear between
them, :class:`~napari_psfspace.core.restore.smooth_grid.SmoothGrid`), one set per plane,
and ``L`` the nodes' graph Laplacian across the plane and to the planes above and below.
``H`` is the 3D operator on lateral blocks
(:class:`~napari_psfspace.core.volume.blocks3d.BlockedOperator3D`, float32). FISTA with
gradient restarts over the two blocks (:class:`~napari_psfspace.core.restore.fista.
BlockFista`), the step from a power iteration on ``H^T H``.

Default weights, as in 2D: ``gamma_1 = ||h|| kappa sigma`` with ``sigma`` the stack's
pixel noise (:func:`~napari_psfspace.core.beads.noise.background_variance` on its
planes), ``||h||`` the l2 norm of the 3D PSF at the field's centre and ``kappa =
sqrt(2 log(N / area))`` (a pure-noise voxel's correlation with the PSF stays below the
threshold); ``gamma_2 = SMOOTH_WEIGHT grid_step^4``.
"""

from __future__ import annotations

import time
from collections.abc import Generator
from dataclasses import dataclass, field

import numpy as np

from ..beads.noise import background_variance
from ..common.device import ArrayModule, array_module, namespace
from ..common.progress import Progress
from ..common.threads import default_workers
from ..common.twins import drained
from ..common.validate import check_finite, check_int, check_signal
from ..restore.deconvolve import BLOCK_SPLIT, NORM_MARGIN, SMOOTH_WEIGHT
from ..restore.fista import BlockFista
from ..restore.smooth_grid import SmoothGrid
from .blocks3d import BLOCK, RTOL, BlockedOperator3D
from .deconvolve3d import check_stack
from .device_plan import plan_on_device
from .operator3d import ProductConvolution3D

#: The float32 volumes of the stack's size the deblurring holds at once (the data, the
#: sparse and smooth parts, their accelerated copies, gradients and the model's image):
#: its memory is checked first.
FISTA_VOLUMES = 10

#: Largest eigenvalue of the nodes' 3D graph Laplacian (6 neighbours): at most 12.
LAPLACIAN_NORM = 12.0
#: Most power iterations for ``||H||^2`` (each one ``H^T H``; stops earlier at 0.1 %).
POWER_ITER = 30
#: float32 volumes the iteration holds at its peak: the data, the iterate, the
#: extrapolated point, the gradient, the prediction's buffer and the smooth part's
#: synthesis (device_plan counts them on a GPU).
FISTA_VOLUMES = 6


@dataclass
class Deblurred3D:
    """Result of :func:`deblur_3d`.

    Attributes
    ----------
    sparse, smooth : ndarray of shape (Z, H, W), float32
        ``u_1`` and ``U w``; ``volume`` is their sum.
    iterations : int
    converged : bool
    parameters : dict
        The weights, the grid step, the noise, ``||H||^2``, the kernels per block and the
        seconds.
    objective : list of float
    """

    sparse: np.ndarray
    smooth: np.ndarray
    iterations: int
    converged: bool
    parameters: dict = field(default_factory=dict)
    objective: list = field(default_factory=list)

    @property
    def volume(self) -> np.ndarray:
        return self.sparse + self.smooth


def laplacian_3d(w: np.ndarray) -> np.ndarray:
    """Graph Laplacian of nodes (Z, ny, nx): 6 neighbours, none across the borders
    (on the device ``w`` is on)."""
    out = namespace(w).zeros_like(w)
    for axis in range(3):
        n = w.shape[axis]
        if n < 2:
            continue
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, n - 1), slice(1, n)
        d = w[tuple(hi)] - w[tuple(lo)]
        out[tuple(lo)] += d
        out[tuple(hi)] -= d
    return out


def _power(op, shape, workers, rtol: float = 1e-3, xp=np):
    """``||H||^2`` by power iteration (yields after each application of ``H^T H``), the
    vectors in the array module ``xp``."""
    x = xp.asarray(np.random.default_rng(0).random(shape).astype(np.float32))
    x /= xp.linalg.norm(x)
    value = 0.0
    for it in range(POWER_ITER):
        y = op.adjoint(op.apply(x, workers=workers), workers=workers)
        new = float(xp.linalg.norm(y))
        if new == 0:
            return 0.0
        x = y / np.float32(new)
        done = abs(new - value) <= rtol * new
        value = new
        yield Progress("setup", 0.0, f"estimating ||H||: power iteration {it + 1}, "
                                     f"||H||^2 >= {value:.4g}")
        if done:
            break
    return value


def iter_deblur_3d(
    stack,
    operator: ProductConvolution3D,
    *,
    sparse_weight: float | None = None,
    smooth_weight: float | None = None,
    grid_step: float = 64.0,
    max_iter: int = 300,
    tol: float = 1e-4,
    block: int | None = BLOCK,
    rtol: float = RTOL,
    workers: int | None = None,
    device: str | ArrayModule = "auto",
) -> Generator[Progress, None, Deblurred3D]:
    """Sparse + smooth deblurring of a z-stack with a space-varying 3D PSF.

    Parameters
    ----------
    stack : array_like of shape (Z, H, W)
        The blurred volume, image units (background included: the smooth part takes it).
    operator : ProductConvolution3D
    sparse_weight : float, optional
        ``gamma_1`` (image units x PSF norm); default from the noise (module notes).
    smooth_weight : float, optional
        ``gamma_2``; default ``SMOOTH_WEIGHT grid_step^4``.
    grid_step : float
        Pixels between the smooth part's nodes on each plane.
    max_iter : int
    tol : float
        Stop once the objective's running minimum falls by less than ``tol``
        (relatively) over 10 iterations.
    block, rtol
        The operator on lateral blocks, as in
        :func:`~napari_psfspace.core.volume.deconvolve3d.richardson_lucy_3d`.
    workers : int, optional
    device : {"auto", "cpu", "gpu"}
        Where the iteration runs (:mod:`~napari_psfspace.core.common.device`): "auto" is
        the GPU when CuPy imports and sees a device, else the CPU. On the GPU the blocks
        are sized from the device's free memory (``block`` is then not used), the
        volumes stay there when the iteration's :data:`FISTA_VOLUMES` fit beside them,
        else on the host (each block copied over and back). The result is NumPy.

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    Deblurred3D
        ``parameters["device"]`` says where it ran, ``parameters["block"]`` the block.
    """
    t0 = time.perf_counter()
    max_iter, am, y = _checked(stack, operator, max_iter, tol, grid_step, device)
    z, h, w = y.shape
    op, block, xp = _operator(operator, z, am, block, rtol)
    workers = default_workers() if workers is None else workers
    grid = SmoothGrid((h, w), grid_step)
    sigma, psf, g1, g2 = _weights(y, operator, grid_step, sparse_weight, smooth_weight)
    h2 = NORM_MARGIN * float((yield from _power(op, y.shape, workers, xp=xp)))
    if h2 <= 0:
        raise ValueError("`operator` is zero: nothing to deblur with")
    pen = g2 / grid.step ** 2
    c = BLOCK_SPLIT
    lips = [(1.0 + c) * h2,
            (1.0 + 1.0 / c) * h2 * grid.norm2() + 2.0 * pen * LAPLACIAN_NORM ** 2]
    work = _Work(am.asarray(y) if xp is not np else y, xp)
    del y
    solver, synthesis = _solver(op, work, grid, am, xp, g1=g1, pen=pen, lips=lips,
                                blocked=block is not None, workers=workers, gain=psf.sum())
    converged = yield from _run(solver, max_iter, tol)
    u1, nodes = solver.finalize()
    solver.z = []  # the extrapolated point: a volume the result does not need
    work.y = work.buf = None  # two volumes the result does not need (the gradient is done)
    smooth = synthesis(nodes)
    if xp is not np:  # the result comes back to the host
        u1, smooth = am.to_host(u1), am.to_host(smooth)
    if isinstance(op, BlockedOperator3D) and am.gpu:
        op.release()  # its spectra and plans go back to the device
    params = {"sparse_weight": g1, "smooth_weight": g2, "grid_step": grid.step,
              "noise_sd": sigma, "lipschitz": lips, "norm2": h2, "tol": float(tol),
              "max_iter": max_iter, "restarts": solver.restarts,
              "kernels": float(op.n_kernels) if block is not None else operator.n_psf,
              "device": am.name, "block": block,
              "seconds": round(time.perf_counter() - t0, 3)}
    return Deblurred3D(u1.astype(np.float32, copy=False),
                       smooth.astype(np.float32, copy=False),
                       solver.iterations, converged, params, list(solver.objective))


def _checked(stack, operator, max_iter, tol, grid_step, device):
    """``max_iter``, the array module and the stack in float32, checked; one clear line
    for a bad value before any work."""
    check_stack(stack, operator, copies=FISTA_VOLUMES)
    max_iter = check_int(max_iter, "max_iter", minimum=1)
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"`tol` must be a finite number >= 0, got {tol!r}")
    if not (np.isfinite(grid_step) and grid_step >= 2):
        raise ValueError(f"`grid_step` must be at least 2 pixels, got {grid_step!r}")
    am = array_module(device)  # "gpu" without CuPy or a device: one line, no work done
    y = np.asarray(stack, dtype=np.float32)
    if not isinstance(stack, np.ndarray):  # a lazy stack: its values are read here
        check_finite(y, "stack")
    check_signal(y, "stack")  # no light (zeros, a negated stack): nothing to deblur
    return max_iter, am, y


def _operator(operator, depth, am, block, rtol):
    """The operator in blocks (on a GPU, as large as the device's memory allows,
    :mod:`.device_plan`), the block size and the volumes' array module (the device's
    where they fit there)."""
    xp = np
    if am.gpu:
        plan = plan_on_device(operator, depth, am.free_bytes(), volumes=FISTA_VOLUMES)
        if plan.volumes_on_device:
            xp = am.xp
        return BlockedOperator3D(operator, block=plan.block, rtol=rtol, device=am), \
            plan.block, xp
    op = operator if block is None else BlockedOperator3D(operator, block=block, rtol=rtol)
    return op, block, xp


def _weights(y, operator, grid_step, sparse_weight, smooth_weight):
    """The background's noise, the PSF at the field's centre, and ``gamma1`` (the
    universal threshold for the voxels the PSF covers, as in 2-D) and ``gamma2``."""
    z, h, w = y.shape
    sigma = float(np.median([np.sqrt(background_variance(p)[1])
                             for p in y[:: max(1, z // 8)]]))
    psf = operator.kernel_at((h - 1) / 2, (w - 1) / 2)
    energy = float((psf ** 2).sum())
    area = float(psf.sum() ** 2 / max(energy, 1e-300))  # voxels the PSF covers
    kappa = float(np.sqrt(2.0 * np.log(max(z * h * w / area, 2.0))))
    g1 = float(np.sqrt(energy) * kappa * sigma) if sparse_weight is None \
        else float(sparse_weight)
    g2 = SMOOTH_WEIGHT * float(grid_step) ** 4 if smooth_weight is None \
        else float(smooth_weight)
    for name, v in (("sparse_weight", g1), ("smooth_weight", g2)):
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"`{name}` must be a finite number >= 0, got {v!r}")
    return sigma, psf, g1, g2


class _Work:
    """The data and the buffer of ``H u`` the gradient reads, referenced from here alone,
    so that both are freed once the iterations are done."""

    def __init__(self, y, xp):
        self.y = y
        self.buf = xp.empty_like(y)


def _solver(op, work: _Work, grid, am, xp, *, g1, pen, lips, blocked, workers, gain):
    """The block FISTA over the sparse volume and the background's nodes (plane by
    plane on the lateral grid), started with no source and the background at the stack's
    level seen through ``H`` (whose planes sum to about ``gain``); and the nodes'
    synthesis."""
    ry, rx = grid.ry.toarray(), grid.rx.toarray()  # (H, ny), (W, nx)
    if xp is not np:
        ry, rx = am.asarray(ry.astype(np.float32)), am.asarray(rx.astype(np.float32))

    def synthesis(nodes):
        return (ry @ nodes) @ rx.T  # (Z, H, W)

    def analysis(g):
        return (ry.T @ g) @ rx  # (Z, ny, nx)

    def gradient(x):
        u1, nodes = x
        u = synthesis(nodes)
        u += u1
        if not blocked:
            r = op.apply(u, workers=workers)
        else:
            r = op.apply(u, out=work.buf, workers=workers)
        del u  # one volume less while H^T runs: the peak (a 64 x 2048 x 2048 stack)
        r -= work.y
        value = 0.5 * float(xp.vdot(r, r))
        g = op.adjoint(r, workers=workers)
        lw = laplacian_3d(nodes)
        value += pen * float(xp.vdot(lw, lw))
        return [g, analysis(g) + (2.0 * pen) * laplacian_3d(lw)], value

    def prox_sparse(v, t, rows):
        v -= np.float32(t * g1)
        xp.maximum(v, 0, out=v)
        return v

    def prox_smooth(v, t, rows):
        xp.maximum(v, 0, out=v)
        return v

    def penalty_sparse(v, rows):
        return g1 * float(xp.abs(v).sum())

    solver = BlockFista(gradient, [prox_sparse, prox_smooth], lips,
                        penalty=[penalty_sparse, None], workers=workers)
    level = max(float(xp.median(work.y)), 0.0)
    gain = max(float(gain), 1e-12)
    solver.setup([xp.zeros(work.y.shape, np.float32),
                  xp.full((work.y.shape[0], *grid.grid_shape), level / gain, np.float32)])
    return solver, synthesis


def _run(solver, max_iter, tol):
    """The solver's iterations, a record after each; whether it converged."""
    run = solver.run(max_iter, tol)
    while True:
        try:
            it, change = next(run)
        except StopIteration as done:
            return bool(done.value)
        yield Progress("deblur", it / max_iter, f"iteration {it}: iterate change "
                                                f"{change:.1e}")


deblur_3d = drained(iter_deblur_3d, "deblur_3d")


__all__ = ["FISTA_VOLUMES", "LAPLACIAN_NORM", "POWER_ITER", "Deblurred3D", "deblur_3d",
           "iter_deblur_3d", "laplacian_3d"]
