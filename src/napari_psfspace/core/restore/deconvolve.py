"""Sparse + smooth deconvolution with a known operator (paper, Appendix D).

The image ``y`` is point sources ``u1`` (beads) on a smooth background ``u2``:

    min_{u1 >= 0, u2 >= 0}  1/2 ||H (u1 + u2) - y||^2 + gamma1 ||u1||_1 + gamma2 ||Lap u2||^2.

**The smooth part lives on a coarse grid.** ``u2 = U w``: the bilinear interpolation of
``w >= 0`` on nodes every ``grid_step`` pixels (so ``u2 >= 0`` wherever ``w`` is), and
``||Lap u2||^2`` is taken as the nodes' discrete Laplacian, ``||L w||^2 / s^2`` for a
grid step ``s`` (its value for a smooth ``u2``). On the pixel grid, the term
``gamma2 ||Lap u2||^2`` has curvature up to ``128 gamma2`` against the data term's 1
or less: one step size for both parts makes the background converge hundreds of times
slower than the beads. On the coarse grid both blocks are well scaled (see
:mod:`.fista`: one step per block).

**The tail by coordinate descent.** FISTA finds the support of ``u1`` in about a hundred
iterations and then spends most of its time concentrating each source's cluster
(neighbouring pixels are nearly the same column of ``H``); by default it stops at
``POLISH_AFTER`` and :mod:`.polish` finishes on the support, one pixel at a time
(``polish``): one pixel at a time is exact there and reaches a lower objective in less
time, with sharper beads (``bench/bench_deblur_tol.py``).

**Refitting the amplitudes** (``debias``). The l1 term shrinks each amplitude by about
``gamma1 / ||h||^2``; a least-squares refit of one scale per cluster of points
(8-connected), with the background free (at most ``DEBIAS_MAX_ITER`` iterations), gives
it back (``bench/bench_deblur.py``). It is off by default: the refit also raises every
spurious point the l1 term let through (noise that correlates with the PSF) to about the
detection level, so that amplitudes no longer tell them from real points.

**Saturation.** A clipped bead, fitted as measured, has its flux pulled down by its
clipped top; pixels at or above ``saturation`` only bound ``H u`` from below.

Defaults follow the image's noise (its background's standard deviation ``sigma``,
:func:`~napari_psfspace.core.beads.noise.background_variance`) and the operator's own
error:

- ``gamma1(x) = ||h||_2 sqrt((kappa sigma)^2 + (eps e(x))^2)``, a weight per pixel:
  ``h`` the PSF at the centre of the field, ``kappa = sqrt(2 ln(N / A))`` for ``N``
  pixels and the PSF's effective area ``A = 1 / sum h^2``, ``e(x)`` the l2 norm of the
  image above its background level over the PSF's area around ``x``, and ``eps`` the
  operator's relative error beyond the noise (``model_error``: from the identification,
  or from a learnt model's held-out residual). Where there is no source,
  ``H^T (y - H u)`` is ``H^T`` of the noise, of standard deviation ``sigma ||h||_2``,
  smooth over about ``A`` pixels; ``u1``
  stays 0 wherever it stays below ``gamma1``, which it does over the whole image with
  high probability (the universal threshold for ``N / A`` independent values). Near a
  bright bead the residual is the operator's error, about ``eps`` of the signal, not
  the noise, and ``|<h_x, r>| <= ||h|| eps e(x)``: the second term keeps the sparse part
  from fitting that error. With the noise alone, the sparse part fits it with rings
  of spurious points around bright beads, whose residual stands above the noise
  (``bench/bench_deblur_measured.py``);
- ``gamma2 = SMOOTH_WEIGHT * s^4``: relative to the data term on one node's cell, the
  penalty on a bump of one node is the same for every grid step (both terms are
  quadratic, so it does not depend on the noise).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from ..beads.noise import background_variance
from ..common.device import ArrayModule, array_module
from ..common.progress import Progress
from ..common.twins import drained
from ..common.validate import (
    as_array,
    as_image,
    check_grid_step,
    check_instance,
    check_int,
    check_memory,
    check_saturation,
    check_signal,
)
from ..model.compress import compress_operator
from ..model.heldout import beyond_noise
from ..model.operator import ProductConvolution
from .fista import BlockFista
from .norm import iter_operator_norm2
from .polish import polish_support
from .smooth_grid import SmoothGrid

#: ``gamma2 = SMOOTH_WEIGHT * grid_step**4`` by default.
SMOOTH_WEIGHT = 0.05
#: The float32 images of the image's size the deblurring holds beside its operator's
#: maps and spectra: the data, the sparse and smooth parts and their accelerated
#: copies, gradients, weights and the censored mask.
DEBLUR_IMAGES = 12
#: Iterations at most of the amplitudes' refit (``debias``).
DEBIAS_MAX_ITER = 100
#: ``c`` of the blocks' majorisation ``||H(u1 + U w)||^2 <= (1 + c) ||H u1||^2 +
#: (1 + 1/c) ||H U w||^2`` (any c > 0 is valid). 1 halves the sparse block's step; 0.25
#: gives it 0.8 of the full step and the few background nodes 0.2: fewer iterations for
#: the same result (``bench/bench_deblur.py``).
BLOCK_SPLIT = 0.25
#: With ``polish``, FISTA runs to this tolerance (its support found), then coordinate
#: descent on the support to ``tol`` (:mod:`.polish`); the tolerance is the loosest that
#: changes no figure of ``bench/bench_deblur_tol.py``. What FISTA leaves off the support,
#: the optimality check after the sweeps sends back to it.
POLISH_AFTER = 3e-3
#: Sweeps at most of the coordinate descent.
POLISH_MAX_SWEEPS = 300
#: Largest support polished (pixels; a sweep is a Python loop over them); beyond it
#: FISTA runs on to ``tol``.
POLISH_MAX_SUPPORT = 60000
#: A pixel off the support whose correlation with the residual exceeds its weight by
#: more than this (relatively) sends the run back to FISTA after the polish.
KKT_SLACK = 1e-3
#: The operator is compressed to this fraction of its own error (``model_error``) by
#: default: a tenth (errors in quadrature: 0.5 % more error) changes no figure of
#: ``bench/bench_deblur_tol.py``, a third does.
COMPRESSION = 0.1
#: With ``polish``, FISTA's search for the support uses the operator compressed to this
#: fraction of its error (the sweeps, the optimality check and any FISTA after them use
#: the operator compressed to ``compression``): fewer kernels where exactness does not
#: matter yet.
SEARCH_COMPRESSION = 0.3
#: Margin on the power-iteration estimate of ``||H||^2`` (run until an iteration adds
#: less than 0.1 %, which leaves the estimate within a fraction of a per cent below the
#: norm; a wider margin costs iterations, ``bench/bench_deblur_tol.py``).
NORM_MARGIN = 1.05


@dataclass
class Deblurred:
    """The result of :func:`deblur`.

    Attributes
    ----------
    sparse : ndarray of shape (H, W), float32
        ``u1``: the point sources (non-negative).
    smooth : ndarray of shape (H, W), float32
        ``u2``: the smooth background (non-negative).
    objective : list of float
        The objective at each iteration's extrapolated point (the sparse + smooth
        problem; the refit of the amplitudes is not in it).
    iterations : int
        FISTA's iterations (with ``polish``: before and after the sweeps, which are
        counted apart in ``parameters``).
    converged : bool
        The objective fell by less than ``tol`` (relatively) over the last 10 iterations
        (or sweeps of the polish) before ``max_iter`` (or the polish's sweeps ran out).
    parameters : dict
        ``sparse_weight`` (the median of its map), ``model_error``, ``smooth_weight``,
        ``grid_step``, ``noise_sd``, ``lipschitz``, ``tol``, ``max_iter``, ``seconds``,
        ``restarts``, ``debias``, ``compression`` and ``kernels`` (the operator's
        kernels before and after compressing it), ``search_kernels`` (those of the
        operator FISTA searched the support with, ``SEARCH_COMPRESSION``),
        ``polish_sweeps`` and, after a polish,
        ``polish`` (its sweeps, supports before and after, pixels that wanted in,
        seconds); after a refit of the amplitudes also
        ``debias_iterations``, ``debias_converged`` and ``amplitude_gain`` (the sparse
        part's total after the refit over before).
    """

    sparse: np.ndarray
    smooth: np.ndarray
    objective: list[float] = field(default_factory=list)
    iterations: int = 0
    converged: bool = False
    parameters: dict = field(default_factory=dict)

    @property
    def image(self) -> np.ndarray:
        """``u1 + u2``: the deblurred image."""
        return self.sparse + self.smooth


def model_error_of(op: ProductConvolution) -> float:
    """The operator's relative error beyond the noise, from its metadata: the
    identification's ``model_error``, else ``sqrt(residual^2 - floor^2)`` of a learnt
    model's held-out beads, else 0."""
    meta = op.metadata or {}
    ident = meta.get("identification") or {}
    if ident.get("model_error") is not None:
        return float(ident["model_error"])
    held = meta.get("heldout") or {}
    if held.get("residual_mean") is not None and held.get("noise_floor_mean") is not None:
        return beyond_noise(held["residual_mean"], held["noise_floor_mean"])
    return 0.0


def default_weights(image: np.ndarray, op: ProductConvolution, grid_step: float, *,
                    model_error: float = 0.0) -> tuple[np.ndarray, float, float]:
    """``(gamma1 map (H, W) float32, gamma2, sigma)``: the defaults of the module's
    docstring."""
    level, var, _ = background_variance(image)
    sigma = float(np.sqrt(var))
    h, w = op.image_shape
    psf = op.psf_at((h - 1) / 2, (w - 1) / 2)
    energy = float((psf ** 2).sum())
    area = 1.0 / max(energy, 1e-300)
    kappa = float(np.sqrt(2.0 * np.log(max(h * w / area, 2.0))))
    norm = float(np.sqrt(energy))
    if model_error > 0:
        # |<h_x, r>| <= ||h|| ||r|| over the PSF's reach, and the operator's error r is
        # about eps of the signal there: ||y - level|| over the PSF's area around x
        width = float(np.sqrt(area / (4 * np.pi)))  # a Gaussian's sigma of that area
        local = np.sqrt(area * ndi.gaussian_filter(np.clip(image - level, 0, None) ** 2,
                                                   width))
        gmap = norm * np.sqrt((kappa * sigma) ** 2 + (model_error * local) ** 2)
    else:
        gmap = np.full(image.shape, norm * kappa * sigma)
    return gmap.astype(np.float32), SMOOTH_WEIGHT * float(grid_step) ** 4, sigma


def iter_deblur(
    image: np.ndarray,
    operator: ProductConvolution,
    *,
    sparse_weight: float | None = None,
    smooth_weight: float | None = None,
    grid_step: float | None = None,
    model_error: float | None = None,
    max_iter: int = 500,
    tol: float = 1e-4,
    debias: bool = False,
    saturation: float | None = None,
    compression: float | None = None,
    polish: bool = True,
    workers: int | None = None,
    device: str | ArrayModule = "auto",
) -> Generator[Progress, None, Deblurred]:
    """Deblur point sources on a smooth background with a known operator.

    Parameters
    ----------
    image : ndarray of shape (H, W)
        The blurred image (any real dtype; processed in float32).
    operator : ProductConvolution
        Its blur (learnt, identified from a family, or simulated).
    sparse_weight : float, optional
        ``gamma1``, one value for every pixel; default a map from the image's noise and
        the operator's error (module docstring; its median is reported).
    smooth_weight : float, optional
        ``gamma2``; default ``0.05 * grid_step**4``.
    grid_step : float, optional
        Node spacing of the background, pixels; default twice the PSF size (finer, it
        forms a bump under each bright bead and takes its flux).
    model_error : float, optional
        The operator's relative error beyond the noise; default from its metadata
        (:func:`model_error_of`). 0: the noise alone sets ``gamma1``.
    max_iter : int
        Iterations at most.
    tol : float
        Stop when the objective falls by less than this (relatively) over 10 iterations;
        looser, the beads stay wider (``bench/bench_deblur_tol.py``).
    debias : bool
        Then refit one scale per cluster of points (module docstring): for photometry
        of points known to be real; no point is added or removed.
    saturation : float, optional
        Pixels at or above it only bound ``H u`` from below in the data term (a clipped
        bead is brighter than it looks). Default: the dtype's maximum for integer
        images, none for floating ones. More than 1 % of the image saturated is an error.
    compression : float, optional
        Run on the operator's PSF field compressed to this relative error
        (:func:`~napari_psfspace.core.model.compress.compress_operator`: the fewest
        kernels whose PSF is within it everywhere); default ``0.1 * model_error`` (a
        family's operator carries more kernels than one image needs). 0: as it is.
    polish : bool
        FISTA until its support is found (``POLISH_AFTER``), then coordinate descent on
        it (:mod:`.polish`), back to FISTA if a pixel off it wants in. Off, or over
        ``POLISH_MAX_SUPPORT`` pixels in the support: FISTA to ``tol``.
    workers : int, optional
        FFT threads.
    device : {"auto", "cpu", "gpu"}
        Where the operator's transforms run (:mod:`~napari_psfspace.core.common.device`;
        "auto": the GPU where CuPy sees one); the iterate and the polish stay on the host.

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    Deblurred
        Sparse and smooth parts (float32, the image's shape) and the objective history;
        ``parameters["device"]`` says where the transforms ran.
    """
    t0 = time.perf_counter()
    am, y, max_iter, saturation, grid, censored, n_saturated, eps = _checked_inputs(
            image, operator, grid_step, model_error, max_iter, tol, saturation, device)
    sigma, g2, gmap, compression, n_kernels, operator, g1 = _weights(
            operator, sparse_weight, smooth_weight, compression, y, grid, eps)
    lips, search, active, solver, data_gradient, gradient, prox_smooth = yield from _solver(
            operator, tol, polish, workers, am, y, grid, censored, eps, g2, gmap)
    polish_info, converged, objective, iterations, w, u1 = yield from _polish_stage(
            operator, max_iter, tol, polish, y, grid, censored, gmap, active, solver,
            data_gradient)
    params = _parameters(operator, max_iter, tol, debias, saturation, compression, am,
                         grid, n_saturated, eps, sigma, g2, n_kernels, g1, lips, search,
                         solver, polish_info)
    if debias and u1.any():
        u1, w = yield from _refit_amplitudes(u1, w, gradient, prox_smooth, lips, tol, min(
            int(max_iter), DEBIAS_MAX_ITER), workers, params)
    u2 = grid.synthesis(w)
    if am.gpu:  # the kernels' spectra and maps go back to the device
        operator.release()
        search.release()
    params["seconds"] = round(time.perf_counter() - t0, 3)
    refit = params.get("debias_iterations")
    yield Progress("deblur", 1.0, f"{iterations} iterations" + (
        "" if refit is None else f" + {refit} to refit the amplitudes"))
    return Deblurred(u1.astype(np.float32), u2.astype(np.float32), objective, iterations,
                     converged, params)


def _checked_inputs(image, operator, grid_step, model_error, max_iter, tol, saturation, device):
    """The image in float32, the device, the background's grid, the saturated pixels and the model
    error; one clear line for a bad value before any work.
    """
    check_instance(operator, ProductConvolution, "operator",
                   "A family (OperatorFamily) gives its operator for an image with "
                   "identify_operator(image, family).")
    am = array_module(device)  # "gpu" without CuPy or a device: one line, no work done
    raw = np.asarray(as_array(image, "image"))
    y = as_image(image, dtype=np.float32)
    if tuple(y.shape) != tuple(operator.image_shape):
        raise ValueError(f"`image` has shape {tuple(y.shape)}, but `operator` acts on "
                         f"images of shape {tuple(operator.image_shape)}")
    check_memory(operator.working_bytes(np.float32) + DEBLUR_IMAGES * y.nbytes,
                 f"`image` of {y.shape[0]} x {y.shape[1]} pixels deblurred with "
                 f"{operator.n_psf} kernels", hint="Deblur it in parts: psfspace deblur --parts.")
    check_signal(y)
    max_iter = check_int(max_iter, "max_iter", minimum=1)
    saturation = check_saturation(saturation)
    if not tol > 0:
        raise ValueError(f"`tol` must be positive, got {tol!r}")
    step = (check_grid_step(grid_step, y.shape, minimum=2.0) if grid_step is not None
            else 2.0 * operator.psf_size)
    grid = SmoothGrid(y.shape, step)
    if saturation is None and raw.dtype.kind in "ui":
        saturation = float(np.iinfo(raw.dtype).max)
    censored = np.nonzero(y >= saturation) if saturation is not None else None
    n_saturated = 0 if censored is None else len(censored[0])
    if n_saturated == 0:
        censored = None
    elif n_saturated > 0.01 * y.size:
        raise ValueError(f"`image` has {n_saturated} pixels at or above the saturation level "
                         f"{saturation:g} ({100 * n_saturated / y.size:.1f} %, expected at "
                         f"most 1 %): lower the exposure, or pass `saturation` if the level "
                         f"is not the dtype's maximum")
    eps = model_error_of(operator) if model_error is None else float(model_error)
    if not (np.isfinite(eps) and eps >= 0):
        raise ValueError(f"`model_error` must be >= 0, got {model_error!r}")
    return am, y, max_iter, saturation, grid, censored, n_saturated, eps


def _weights(operator, sparse_weight, smooth_weight, compression, y, grid, eps):
    """The sparse weight map, its median, the smoothness weight and the operator compressed as
    asked.
    """
    gmap, g2, sigma = default_weights(y, operator, grid.step, model_error=eps)
    if compression is None:
        compression = COMPRESSION * eps
    if not (np.isfinite(compression) and compression >= 0):
        raise ValueError(f"`compression` must be >= 0, got {compression!r}")
    n_kernels = operator.n_psf
    if compression > 0:
        operator = compress_operator(operator, compression)
    g1 = float(np.median(gmap))
    if sparse_weight is not None:
        if not (np.isfinite(sparse_weight) and sparse_weight >= 0):
            raise ValueError(f"`sparse_weight` must be >= 0, got {sparse_weight!r}")
        g1 = float(sparse_weight)
        gmap = np.full(y.shape, g1, np.float32)
    if smooth_weight is not None:
        if not (np.isfinite(smooth_weight) and smooth_weight >= 0):
            raise ValueError(f"`smooth_weight` must be >= 0, got {smooth_weight!r}")
        g2 = float(smooth_weight)
    return sigma, g2, gmap, compression, n_kernels, operator, g1


def _norm_bound(operator, workers, am):
    """``||H||^2`` by power iteration with the safety margin; one application of ``H^T H`` between
    yields (cancellable).
    """
    yield Progress("setup", 0.0, "estimating ||H||")
    norm = iter_operator_norm2(operator, workers=workers, device=am)
    while True:  # one application of H^T H between yields: cancellable
        try:
            it, value = next(norm)
        except StopIteration as done:
            h2 = NORM_MARGIN * float(done.value)
            break
        yield Progress("setup", 0.0, f"estimating ||H||: power iteration {it}, "
                                     f"||H||^2 >= {value:.4g}")
    return h2


def _solver(operator, tol, polish, workers, am, y, grid, censored, eps, g2, gmap):
    """The block FISTA over the sparse part and the background's grid, its steps from
    ``||H||^2``; started with no source and the background at the image's median."""
    h2 = yield from _norm_bound(operator, workers, am)
    pen = g2 / grid.step ** 2  # gamma2 ||Lap u2||^2 = pen ||L w||^2
    c = BLOCK_SPLIT  # ||H(a + b)||^2 <= (1 + c) ||H a||^2 + (1 + 1/c) ||H b||^2
    lips = [(1.0 + c) * h2, (1.0 + 1.0 / c) * h2 * grid.norm2() + 2.0 * pen * 64.0]

    search = (compress_operator(operator, SEARCH_COMPRESSION * eps)
              if polish and eps > 0 and tol < POLISH_AFTER else operator)
    active = [search]  # the operator of the gradient: the search's, then the exact one
    # on a GPU the data stay there; the gradient's transforms run there, the iterate
    # (two small blocks) on the host
    y_on, censored_on = ((am.asarray(y), None if censored is None else
                          tuple(am.asarray(c) for c in censored)) if am.gpu
                         else (y, censored))

    def data_gradient(op, z):
        g, value = op.data_gradient(z, y_on, censored=censored_on, workers=workers,
                                    device=am)
        return am.to_host(g), value

    def gradient(x):
        u1, w = x
        z = grid.synthesis(w)
        z += u1
        g, value = data_gradient(active[0], z)
        lw = grid.laplacian(w)
        value = 0.5 * value + pen * float(np.vdot(lw, lw))
        return [g, grid.adjoint(g) + (2.0 * pen) * grid.laplacian(lw)], value

    thresholds = {}

    def prox_sparse(v, t, rows):  # soft threshold at t gamma1(x), then >= 0
        if t not in thresholds:  # the step is fixed: scale the map once
            thresholds[t] = gmap * np.float32(t)
        v -= thresholds[t][rows]
        np.maximum(v, 0, out=v)
        return v

    def prox_smooth(v, t, rows):
        np.maximum(v, 0, out=v)
        return v

    def penalty_sparse(v, rows):
        return float(np.vdot(gmap[rows], np.abs(v)))

    solver = BlockFista(gradient, [prox_sparse, prox_smooth], lips,
                        penalty=[penalty_sparse, None], workers=workers)
    # start: no source, the background at the image's level seen through H
    level = max(float(np.median(y)), 0.0)
    solver.setup([np.zeros(y.shape, np.float32),
                  np.full(grid.grid_shape, level, np.float32)])
    return lips, search, active, solver, data_gradient, gradient, prox_smooth


def _polish_stage(operator, max_iter, tol, polish, y, grid, censored, gmap, active, solver,
                  data_gradient):
    """With ``polish``: FISTA until the support is found, then coordinate descent on it; back to
    FISTA to ``tol`` if pixels off the support want in.
    """
    polish_info = None
    # with ``polish``: FISTA until the support is found, then coordinate descent on it
    converged = yield from _iterate(solver, max_iter, max(tol, POLISH_AFTER) if polish
                                    else tol, "deblur")
    iterations, objective = solver.iterations, list(solver.objective)
    u1, w = solver.finalize()
    active[0] = operator
    if polish and converged and tol < POLISH_AFTER:
        n_support = int(np.count_nonzero(u1))
        entering = 0
        if 0 < n_support <= POLISH_MAX_SUPPORT:
            u2 = grid.synthesis(w)
            sweeps = polish_support(y, operator, u1, u2, gmap, censored=censored,
                                    tol=tol, max_sweeps=POLISH_MAX_SWEEPS)
            while True:  # the bar stays where FISTA left it while the sweeps run
                try:
                    step = next(sweeps)
                except StopIteration as end:
                    u1, polish_info = end.value
                    break
                yield Progress(step.stage, iterations / int(max_iter), step.message)
            # optimality off the support (FISTA stopped early: a pixel may still want
            # in): -gradient <= gamma1 wherever u1 = 0
            g, _ = data_gradient(operator, u1 + u2)
            entering = int(np.count_nonzero((u1 == 0) & (-g > gmap * (1.0 + KKT_SLACK))))
            polish_info["entering"] = entering
            converged = bool(polish_info["converged"])
        if polish_info is None or entering:  # no polish, or pixels want in: FISTA to tol
            solver.setup([u1, w])
            converged = yield from _iterate(solver, max(1, int(max_iter) - iterations), tol,
                                            "deblur", done=iterations, total=max_iter)
            iterations += solver.iterations
            objective += solver.objective
            u1, w = solver.finalize()
    return polish_info, converged, objective, iterations, w, u1


def _parameters(operator, max_iter, tol, debias, saturation, compression, am, grid, n_saturated,
                eps, sigma, g2, n_kernels, g1, lips, search, solver, polish_info):
    """The run's parameters as recorded in ``Deblurred.parameters``."""
    params = {"sparse_weight": g1, "model_error": eps, "smooth_weight": g2,
              "grid_step": grid.step,
              "noise_sd": sigma, "lipschitz": lips, "tol": float(tol),
              "max_iter": int(max_iter), "restarts": solver.restarts, "debias": bool(debias),
              "polish_sweeps": 0 if polish_info is None else polish_info["sweeps"],
              "saturation": saturation, "saturated_pixels": n_saturated,
              "compression": float(compression), "kernels": [int(n_kernels),
                                                             int(operator.n_psf)],
              "search_kernels": int(search.n_psf), "device": am.name}
    if polish_info is not None:
        params["polish"] = polish_info
    return params


def _refit_amplitudes(u1: np.ndarray, w: np.ndarray, gradient: Callable,
                      prox_smooth: Callable, lips: list[float], tol: float, max_iter: int,
                      workers: int | None, params: dict
                      ) -> Generator[Progress, None, tuple[np.ndarray, np.ndarray]]:
    """Refit one scale per cluster of points of ``u1`` (8-connected), the background
    free: ``u1 = sum_c v_c phi_c`` with ``phi_c`` the cluster's normalised shape.

    The l1 term shrinks every amplitude by about ``gamma1 / ||h||^2``. Refitting every
    pixel of the support instead was ill-conditioned: neighbouring pixels seen through
    the blur are nearly the same column of ``H``, and the flux moved between them
    (spurious peaks as bright as the points).
    One scale per cluster keeps each cluster's shape; the shapes have disjoint supports
    and unit norm, so ``||H Phi||^2 <= ||H||^2``: the sparse block's step holds.
    """
    labels, n = ndi.label(u1 > 0, structure=np.ones((3, 3), bool))
    idx = np.flatnonzero(labels)
    lab = labels.ravel()[idx] - 1
    vals = u1.ravel()[idx].astype(np.float64)
    norms = np.sqrt(np.bincount(lab, weights=vals ** 2, minlength=n))
    phi = (vals / norms[lab]).astype(np.float32)

    def points(v: np.ndarray) -> np.ndarray:
        out = np.zeros(u1.shape, np.float32)
        out.ravel()[idx] = phi * v[lab]
        return out

    def refit_gradient(x):
        v, wb = x
        (g, gw), value = gradient([points(v), wb])
        gv = np.bincount(lab, weights=phi * g.ravel()[idx], minlength=n)
        return [gv.astype(np.float32), gw], value

    def prox_scale(v, t, rows):
        np.maximum(v, 0, out=v)
        return v

    refit = BlockFista(refit_gradient, [prox_scale, prox_smooth], lips,
                       penalty=[lambda v, rows: 0.0, None], workers=workers)
    refit.setup([norms.astype(np.float32), w])
    params["debias_converged"] = yield from _iterate(refit, max_iter, tol, "debias")
    params["debias_iterations"] = refit.iterations
    params["debias_clusters"] = int(n)
    v, w = refit.finalize()
    new = points(v)
    params["amplitude_gain"] = float(new.sum() / max(float(u1.sum()), 1e-30))
    return new, w


def _iterate(solver: BlockFista, max_iter: int, tol: float, stage: str, *,
             done: int = 0, total: int | None = None) -> Generator[Progress, None, bool]:
    """Run ``solver``, yielding progress after every iteration; returns whether it
    converged. ``done``: iterations already run by an earlier stage, out of ``total``
    (default ``max_iter``), so that the fraction reported never goes back."""
    total = int(max_iter) if total is None else int(total)
    run = solver.run(max_iter, tol)
    while True:
        try:
            it, change = next(run)
        except StopIteration as done:
            return bool(done.value)
        # every iteration: a point to cancel at (an iteration is at most about a second
        # at 2048 x 2048), and a line that says where the run stands
        obj = solver.objective
        if len(obj) > 10:
            text = (f"objective fell {(obj[-11] - obj[-1]) / abs(obj[-1]):.1e} over 10 "
                    f"iterations (stops below {tol:g})")
        else:
            text = "the stopping rule is judged over 10 iterations, from iteration 11"
        yield Progress(stage, min((done + it) / total, 1.0),
                       f"{stage} iteration {it}: {text}; iterate change {change:.1e}")


deblur = drained(iter_deblur, "deblur")
