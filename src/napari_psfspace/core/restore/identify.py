"""Identify the operator of one blurred image from a few of its beads (paper, Appendix D).

A family of operators (:class:`~napari_psfspace.core.subspace.OperatorSubspace`) is known:
``H u = sum_ij Gamma[i, j] h_i * (a_j . u)`` with ``Gamma`` in the cone of the ``Gamma_k``.
Each bead ``p`` of the image, centred and free of background, gives its coefficients
``c_p = <p_p, h_i>``; problem (9) is

    min_{Gamma in C, g in [a, b]^P}  1/2 sum_p || g_p Gamma a(z_p) - c_p ||^2,

with ``g_p`` the unknown amplitude of bead ``p``. It is solved by alternating minimisation,
each step exactly:

- ``Gamma`` given ``g``: every ``Gamma`` of the cone is ``sum_k lambda_k Gamma_k`` with
  ``lambda >= 0``, and ``Gamma a(z_p)`` is linear in ``lambda``: a non-negative least
  squares problem in ``K`` unknowns (``scipy.optimize.nnls``, exact). The paper uses an
  accelerated projected gradient here; an exact solver of a K-unknown problem needs no
  step size or iteration count.
- ``g`` given ``Gamma``: each ``g_p`` is a one-dimensional least squares clipped to
  ``[a, b]``, in closed form.

``P >= J`` beads should identify ``Gamma`` (each bead gives ``I`` equations); with fewer,
the cone alone keeps it plausible.

By default (``prior=True``) the family is a prior rather than a hard constraint: on
wide focus series the cone's ``Gamma`` is far from the truth even identified from all
the image's beads (a condition between those learnt is rarely a non-negative mix of
them). The weights of the ``Gamma_k`` are then left free in sign and vary over the
field as a plane (a tilted focus puts each part of the field under another condition),
and the ``Gamma`` is corrected towards the beads by kernel ridge regression with the
family's spatial kernel (:func:`identify_gamma`; each measured by
``bench/bench_identify_wide.py``). :func:`resample` says how sure it is (the spread of
the PSFs when beads are left out), and a warning (:class:`IdentificationWarning`,
``metadata["identification"]["warning"]``) says when the operator misses the clicked
beads (or one of them) beyond their noise.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import nnls

from ..common.threads import blas_threads
from ..common.validate import as_image, check_instance, check_int
from ..model.heldout import (
    beyond_noise,
    beyond_noise_each,
    heldout_residuals,
    median_beyond_noise,
    residuals_of,
    split_holdout,
)
from ..model.operator import ProductConvolution
from ..subspace.choice import Choice, blend, choose_between, own_estimate
from ..subspace.patches import image_patches
from ..subspace.result import OperatorSubspace, space_at

#: Default range of the beads' amplitudes relative to the family's (patches are
#: normalised to unit flux, so 1 is a bead whose flux was measured exactly).
AMPLITUDE_RANGE = (0.5, 2.0)


def _coefficients(psf: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (P, I) of patches (P, S, S) on the basis (I, S, S) (the
    refitted basis images are not exactly orthonormal)."""
    b = basis.reshape(len(basis), -1)
    return np.linalg.lstsq(b.T, psf.reshape(len(psf), -1).T, rcond=None)[0].T


def solve_identification(c: np.ndarray, v: np.ndarray, *,
                         amplitude_range: tuple[float, float] = AMPLITUDE_RANGE,
                         max_iter: int = 100, tol: float = 1e-8,
                         prior: np.ndarray | None = None, sd: np.ndarray | None = None,
                         n_slopes: int = 0
                         ) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """Problem (9) in the cone's weights.

    Parameters
    ----------
    c : ndarray of shape (P, I)
        Coefficients of the beads' patches.
    v : ndarray of shape (K, P, I)
        ``Gamma_k a(z_p)``: the coefficients image ``k``'s operator has at each bead.
    amplitude_range : (float, float)
        ``[a, b]``, ``0 < a <= 1 <= b``.
    max_iter, tol
        Alternations at most; stop when the objective changes by less than ``tol``
        relatively.
    prior : ndarray of shape (K,), optional
        Weights free in sign instead, with a Gaussian prior centred on ``prior`` (the
        cone's solution) of standard deviation its rms: the beads' coefficients, each
        weighted by its noise ``sd``, move the weights away from the cone as far as
        their noise allows (bright beads: the span of the ``Gamma_k``; faint beads: the
        cone).
    sd : ndarray of shape (P,), optional
        Noise standard deviation of each bead's coefficients (default 1: then the prior
        is only the small :data:`WEIGHT_RIDGE`).
    n_slopes : int
        With ``prior``: the last ``n_slopes`` of the ``K`` weights are slopes of the
        weights over the field (:func:`identify_gamma`), centred on 0 with the ridge
        :data:`SLOPE_RIDGE`; the others are the weights proper.

    Returns
    -------
    weights : ndarray of shape (K,)
        ``lambda >= 0``: ``Gamma = sum_k lambda_k Gamma_k``.
    amplitudes : ndarray of shape (P,)
    objective : list of float
        ``1/2 sum_p ||g_p Gamma a(z_p) - c_p||^2`` after each alternation.
    """
    a, b = (float(x) for x in amplitude_range)
    if not 0 < a <= 1 <= b:
        raise ValueError(f"`amplitude_range` must be (a, b) with 0 < a <= 1 <= b, got "
                         f"{amplitude_range!r}")
    n_k, n_p, n_i = v.shape
    g = np.ones(n_p)
    history: list[float] = []
    lam = np.zeros(n_k)
    for _ in range(int(max_iter)):
        m_mat = (g[None, :, None] * v).reshape(n_k, n_p * n_i).T  # (P I, K)
        if prior is None:
            lam, _ = nnls(m_mat, c.ravel(), maxiter=50 * n_k)
        else:
            w = np.repeat(1.0 / np.asarray(sd, np.float64) ** 2, n_i) if sd is not None \
                else np.ones(n_p * n_i)
            normal = m_mat.T @ (w[:, None] * m_mat)
            mean_diag = max(float(np.trace(normal)) / n_k, 1e-300)
            n_w = n_k - int(n_slopes)
            eps = WEIGHT_RIDGE * mean_diag
            if sd is not None:
                eps = max(eps, 1.0 / max(float(np.mean(prior[:n_w] ** 2)), 1e-300))
            reg = np.full(n_k, eps)
            reg[n_w:] = SLOPE_RIDGE * mean_diag
            lam = np.linalg.solve(normal + np.diag(reg), m_mat.T @ (w * c.ravel()) + reg * prior)
        m = np.tensordot(lam, v, axes=1)  # (P, I)
        mm = (m * m).sum(axis=1)
        g = np.where(mm > 0, (m * c).sum(axis=1) / np.maximum(mm, 1e-300), 1.0).clip(a, b)
        history.append(0.5 * float(((g[:, None] * m - c) ** 2).sum()))
        if len(history) > 1 and abs(history[-2] - history[-1]) <= tol * max(history[-2],
                                                                           1e-300):
            break
    return lam, g, history


#: Ridge of the correction of the family's ``Gamma`` towards the beads, relative to the
#: mean squared norm of the spatial basis at the beads (:func:`correction`). Chosen on
#: wide focus series, bright and faint beads (``bench/bench_identify_wide.py``): a
#: decade either way of the plateau it sits on. Leaving beads out does not choose it
#: reliably from 5 beads, so it is fixed.
CORRECTION_RIDGE = 0.1
#: Tikhonov weight that keeps the weights of the ``Gamma_k`` near the cone's solution
#: where the beads leave them undetermined (more images than equations), relative to
#: the mean diagonal of the normal matrix.
WEIGHT_RIDGE = 1e-3
#: Folds of the resampling over the beads (leave-one-bead-out below this count).
N_FOLDS = 5
#: The warning's bound on the identified operator's error on the clicked beads, beyond
#: their noise (relative l2 of the PSF; ``model_error``, measured on the beads it was
#: fitted to), in units of the family's own error on beads it never saw (the median
#: over its images of the same measure on their held-out beads). The bound separates,
#: on wide focus series, the images whose operator is more than twice as far from the
#: truth as one estimated from all their beads from the others, and passes the measured
#: stacks (``bench/bench_identify_wide.py``, bench/RESULTS.md).
WARN_RATIO = 1.1
#: The bound without held-out figures (a family learnt with ``holdout=None``), and its
#: floor otherwise.
WARN_MODEL_ERROR = 0.1
WARN_FLOOR = 0.03
#: The warning's bound on the worst clicked bead, in units of ``warning_bound``: the
#: median (``model_error``) hides one bead of five that the family cannot explain (a
#: corner of a tilted field beyond the focus learnt: its PSF a third outside the
#: family's PSF basis; an unresolved pair). Set above the worst bead of 5 on all but a
#: few images of wide focus series (``bench/bench_identify_wide.py``; bench/RESULTS.md).
WARN_BEAD_RATIO = 4.0


def family_model_error(subspace: OperatorSubspace) -> float | None:
    """The family's error beyond the noise on beads it never saw: the median over its
    images of ``sqrt(residual^2 - floor^2)`` of their held-out beads (None without)."""
    held = [h for h in subspace.metadata.get("heldout") or []
            if h.get("n_beads") and h.get("residual_mean") is not None]
    if not held:
        return None
    return float(np.median([beyond_noise(h["residual_mean"], h["noise_floor_mean"])
                            for h in held]))


def warn_bound(subspace: OperatorSubspace) -> float:
    """The ``model_error`` above which :func:`identify_operator` warns."""
    ref = family_model_error(subspace)
    return WARN_MODEL_ERROR if ref is None else max(WARN_FLOOR, WARN_RATIO * ref)


def correction(at: np.ndarray, residual: np.ndarray, ridge: float) -> np.ndarray:
    """The smallest change of ``Gamma`` (I, J) that explains the beads' residual
    coefficients (P, I) at their spatial basis values ``at`` (P, J), with ridge ``ridge``:
    kernel ridge regression with the family's own spatial kernel ``a(x) . a(y)`` (a
    Gaussian prior on ``Gamma`` centred on the family's)."""
    if not np.isfinite(ridge):
        return np.zeros((residual.shape[1], at.shape[1]))
    k = at @ at.T  # (P, P)
    alpha = np.linalg.solve(k + ridge * np.eye(len(k)), residual)  # (P, I)
    return (at.T @ alpha).T  # (I, J)


def _centred(subspace: OperatorSubspace, points: np.ndarray) -> np.ndarray:
    """Positions (row, column), pixels, scaled to the image and centred: -0.5 to 0.5."""
    return np.asarray(points, np.float64) / np.asarray(subspace.shape, np.float64) - 0.5


def _nodes(subspace: OperatorSubspace) -> np.ndarray:
    """The grid's nodes (G, 2), pixels, in the order of the spatial basis's pixels."""
    gy, gx = subspace.grid
    return np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)


def affine_maps(subspace: OperatorSubspace) -> np.ndarray:
    """The maps ``1``, ``y`` and ``x`` over the field (coordinates scaled to the image,
    centred) expressed on the family's spatial basis, shape (3, J)."""
    at_nodes = _centred(subspace, _nodes(subspace))
    plane = np.column_stack([np.ones(len(at_nodes)), at_nodes])
    return plane.T @ subspace.space.reshape(subspace.n_space, -1).T


def slope_frame(subspace: OperatorSubspace, centers: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What :func:`identify_gamma` needs for weights that vary over the field: the
    centred coordinates (row, column, scaled to the image: -0.5 to 0.5) of the beads at
    ``centers`` (P, 2) and of the grid's nodes (G, 2), and the spatial basis at the
    nodes (G, J)."""
    return (_centred(subspace, centers), _centred(subspace, _nodes(subspace)),
            subspace.space.reshape(subspace.n_space, -1).T)


def affine_correction(at: np.ndarray, residual: np.ndarray, affine: np.ndarray,
                      sd: np.ndarray | None = None) -> np.ndarray:
    """The change of ``Gamma`` (I, J) whose maps are affine over the field (``affine``,
    (3, J), :func:`affine_maps`) that best explains the beads' residual coefficients
    (P, I) at ``at`` (P, J): weighted least squares, each bead by its noise ``sd`` (P,),
    with a ridge of :data:`AFFINE_RIDGE`; zero below 4 beads."""
    if len(at) < 4:
        return np.zeros((residual.shape[1], affine.shape[1]))
    x = at @ affine.T  # (P, 3): the affine maps at the beads
    w = np.ones(len(x)) if sd is None else 1.0 / np.maximum(np.asarray(sd, float), 1e-300) ** 2
    normal = x.T @ (w[:, None] * x)
    ridge = AFFINE_RIDGE * max(float(np.trace(normal)) / 3.0, 1e-300)
    b = np.linalg.solve(normal + ridge * np.eye(3), x.T @ (w[:, None] * residual))  # (3, I)
    return b.T @ affine


#: Ridge of the affine correction, relative to the mean diagonal of its normal matrix.
AFFINE_RIDGE = 1e-3


def identify_gamma(c: np.ndarray, at: np.ndarray, gammas: np.ndarray, *,
                   prior: bool = True, sd: np.ndarray | None = None,
                   amplitude_range=AMPLITUDE_RANGE,
                   max_iter: int = 100,
                   affine: np.ndarray | None = None,
                   slopes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """``Gamma`` (I, J) of the beads' coefficients ``c`` (P, I) at ``at`` (P, J).

    ``prior=False``: the paper's problem (9), ``Gamma`` in the cone of the ``Gamma_k``.
    ``prior=True``: the family as a prior: the weights of the ``Gamma_k`` free in sign
    (a condition between those learnt is rarely a non-negative mix of them; kept near
    the cone's solution by :data:`WEIGHT_RIDGE` where undetermined; with ``slopes``
    (:func:`slope_frame`), the weights vary over the field as a plane, its slopes kept
    near 0 by :data:`SLOPE_RIDGE`: a tilted focus puts one part of the field under one
    learnt condition and another part under another), then, with
    ``affine`` (:func:`affine_maps`), the :func:`affine_correction` (a focus shift and a
    tilt of the slide move the whole field; a few beads determine an affine change
    where they do not determine a free one), then the kernel ridge :func:`correction`
    towards the beads. The operator's PSFs are still kept in the cone of observed PSFs
    when it is built.

    Returns
    -------
    gamma : ndarray of shape (I, J)
        With ``slopes``, the one whose coefficients are nearest those of the weights
        varying over the field, at the grid's nodes.
    weights : ndarray of shape (K,)
        The weights at the centre of the field.
    amplitudes : ndarray of shape (P,)
    objective : list of float
    """
    v = np.einsum("pj,kij->kpi", at, gammas)  # (K, P, I)
    lam, g, history = solve_identification(c, v, amplitude_range=amplitude_range,
                                           max_iter=max_iter)
    gamma = None
    if prior and slopes is not None:
        at_beads, at_nodes, space_nodes = slopes
        n_k = len(gammas)
        v3 = np.concatenate([v, v * at_beads[None, :, 0, None], v * at_beads[None, :, 1, None]])
        w3, g, more = solve_identification(c, v3, amplitude_range=amplitude_range,
                                           max_iter=max_iter, sd=sd, n_slopes=2 * n_k,
                                           prior=np.concatenate([lam, np.zeros(2 * n_k)]))
        history = history + more
        lam = w3[:n_k]
        field = lam + at_nodes @ w3[n_k:].reshape(2, n_k)  # (G, K): the weights at the nodes
        coef = np.einsum("gk,kij,gj->gi", field, gammas, space_nodes)  # (G, I)
        gamma = np.linalg.lstsq(space_nodes, coef, rcond=None)[0].T
    elif prior:
        lam, g, more = solve_identification(c, v, amplitude_range=amplitude_range,
                                            max_iter=max_iter, prior=lam, sd=sd)
        history = history + more
    if gamma is None:
        gamma = np.tensordot(lam, gammas, axes=1)
    if prior and affine is not None:
        gamma = gamma + affine_correction(at, c / g[:, None] - at @ gamma.T, affine, sd)
    if prior:
        scale = float(np.mean((at * at).sum(axis=1))) or 1.0
        gamma = gamma + correction(at, c / g[:, None] - at @ gamma.T,
                                   CORRECTION_RIDGE * scale)
    return gamma, lam, g, history


#: Ridge of the slopes of the ``Gamma_k``'s weights over the field (:func:`identify_gamma`),
#: relative to the mean diagonal of the normal matrix. Chosen on wide focus series from 5
#: beads (``bench/bench_identify_wide.py``), at the upper end of a plateau spanning a
#: decade, where 5 random beads of a narrow faint family lose nothing against the
#: weights without slopes (``tests/test_restore.py``); figures in bench/RESULTS.md.
SLOPE_RIDGE = 0.01


#: Fewest usable beads at which the identified operator is judged against the image's own
#: estimate on held-out beads (a fifth of them): with as many, the image's own estimate
#: is a real alternative, and the identification is kept no worse than it (blended with
#: it, or replaced, as the family's images are: :mod:`~napari_psfspace.core.subspace.
#: choice`). From all of an image's beads the identified operator could be worse than
#: ``estimate_operator`` on wide focus series (``bench/bench_identify_wide.py``, column
#: ``all``; bench/RESULTS.md).
MIN_BEADS_JUDGED = 15


def judge_against_own(patches, c: np.ndarray, at: np.ndarray, subspace: OperatorSubspace,
                      *, prior: bool = True, sd: np.ndarray | None = None,
                      amplitude_range=AMPLITUDE_RANGE, max_iter: int = 100
                      ) -> Choice | None:
    """The family's weight against the image's own estimate, on held-out beads.

    About a fifth of the beads, spread over the field, are held out; the operator
    identified from the others and the image's own estimate from the same others
    (:func:`~napari_psfspace.core.subspace.choice.own_estimate`) are blended at each
    weight and judged on them (:func:`~napari_psfspace.core.subspace.choice.
    choose_between`). None below :data:`MIN_BEADS_JUDGED` beads.
    """
    if len(c) < MIN_BEADS_JUDGED:
        return None
    mask = split_holdout(patches.centers, subspace.shape)
    if not mask.any() or mask.all():
        return None
    gam, *_ = identify_gamma(c[~mask], at[~mask], subspace.gammas, prior=prior,
                             sd=None if sd is None else sd[~mask],
                             amplitude_range=amplitude_range, max_iter=max_iter,
                             affine=affine_maps(subspace),
                             slopes=slope_frame(subspace, patches.centers[~mask]))
    held = patches.subset(mask)
    own = own_estimate(patches.subset(~mask), subspace.shape, grid_step=subspace.grid_step,
                       n_image=len(c))
    return choose_between(subspace.psfs_of(gam, held.centers), own, held)


class IdentificationWarning(UserWarning):
    """The family does not explain the beads an operator was identified from."""


def resample(patches, c: np.ndarray, at: np.ndarray, subspace: OperatorSubspace, *,
             prior: bool = True, sd: np.ndarray | None = None,
             amplitude_range=AMPLITUDE_RANGE, max_iter: int = 100, n_folds: int = N_FOLDS,
             n_grid: int = 4) -> dict:
    """How sure an identification is, by leaving beads out.

    Each fold of the beads (one bead each below ``n_folds`` beads) is predicted by the
    operator identified from the others.

    Returns
    -------
    dict
        ``cv_residual_median`` and ``cv_noise_floor_median`` (the left-out beads'
        relative residuals and their noise), ``cv_model_error`` (``sqrt(median
        residual^2 - median floor^2)``: the error of the operator on beads it did not
        see, beyond their noise; None below 3 beads), ``psf_spread`` (the jackknife
        standard deviation of the PSFs over the folds at an ``n_grid x n_grid`` grid of
        the field, relative to their norm, averaged; None below 3 beads), ``n_folds``.
    """
    n_p = len(c)
    if n_p < 3:
        return {"cv_residual_median": None, "cv_noise_floor_median": None,
                "cv_model_error": None, "psf_spread": None, "n_folds": 0}
    folds = np.arange(n_p) % min(int(n_folds), n_p)
    h, w = subspace.shape
    grid = np.stack(np.meshgrid((np.arange(n_grid) + 0.5) * h / n_grid,
                                (np.arange(n_grid) + 0.5) * w / n_grid, indexing="ij"),
                    axis=-1).reshape(-1, 2)
    res, floor, psfs = np.empty(n_p), np.empty(n_p), []
    affine = affine_maps(subspace)
    for f in np.unique(folds):
        out = folds == f
        gam, *_ = identify_gamma(c[~out], at[~out], subspace.gammas, prior=prior,
                                 sd=None if sd is None else sd[~out],
                                 amplitude_range=amplitude_range, max_iter=max_iter,
                                 affine=affine,
                                 slopes=slope_frame(subspace, patches.centers[~out]))
        left = patches.subset(out)
        r = residuals_of(subspace.psfs_of(gam, left.centers), left)
        res[out], floor[out] = r.residual, r.noise_floor
        psfs.append(subspace.psfs_of(gam, grid))
    psfs = np.array(psfs)  # (F, G, P, P)
    n_f = len(psfs)
    dev = psfs - psfs.mean(axis=0)
    var = (n_f - 1) / n_f * (dev ** 2).sum(axis=(0, 2, 3))  # jackknife, per position
    spread = np.sqrt(var) / np.linalg.norm(psfs.mean(axis=0), axis=(1, 2))
    return {"cv_residual_median": float(np.median(res)),
            "cv_noise_floor_median": float(np.median(floor)),
            "cv_model_error": median_beyond_noise(res, floor),
            "psf_spread": float(spread.mean()), "n_folds": int(n_f)}


@blas_threads
def identify_operator(
    image: np.ndarray,
    subspace: OperatorSubspace,
    *,
    beads: np.ndarray | None = None,
    psf_radius: float | None = None,
    threshold: float = 8.0,
    amplitude_range: tuple[float, float] = AMPLITUDE_RANGE,
    max_iter: int = 100,
    prior: bool = True,
) -> ProductConvolution:
    """The operator of the family that explains the beads of one image (problem (9)).

    Parameters
    ----------
    image : ndarray of shape (H, W)
        The blurred image, of the shape the family was learnt on.
    subspace : OperatorSubspace
        The family of operators (:func:`~napari_psfspace.core.subspace.estimate_subspace`).
    beads : ndarray of shape (N, 2), optional
        Bead positions (row, column), pixels, e.g. a Points layer's; they are centred
        sub-pixel and checked (border, neighbours, saturation). Default: detected.
    psf_radius : float, optional
        Patch radius, pixels; default the family's (it must give the family's patch
        size).
    threshold : float
        Detection threshold (noise standard deviations), when ``beads`` is None.
    amplitude_range : (float, float)
        ``[a, b]``: range of each bead's amplitude relative to the family's.
    max_iter : int
        Alternations at most.
    prior : bool
        The family as a prior (default; see the module's notes) rather than the paper's
        hard constraint (``False``: ``Gamma`` in the cone of the ``Gamma_k``).

    Returns
    -------
    ProductConvolution
        Its PSFs sum to 1 and lie in the family's cone (or, blended with the image's own
        estimate, between the two). ``metadata["identification"]``
        holds ``gamma`` (I, J), the cone ``weights`` (K,), the beads' ``positions`` and
        ``amplitudes``, the ``objective`` history, ``n_beads``, and how well the
        operator fits those beads: the median relative residual of their patches, its
        noise floor, and ``model_error = sqrt(median residual^2 - median floor^2)``, the
        relative error of the operator beyond the noise (which
        :func:`~napari_psfspace.core.restore.deconvolve.deblur` allows for); how sure it
        is (:func:`resample`: ``psf_spread``, ``cv_model_error``, ...); ``warning``
        (None, or why: the family does not explain the beads, ``model_error`` above
        ``warning_bound``, :func:`warn_bound`, or one of them, by more than
        :data:`WARN_BEAD_RATIO` times that bound; an :class:`IdentificationWarning` is
        issued too) and ``prior``; ``choice`` (None below :data:`MIN_BEADS_JUDGED`
        beads; else the held-out judgement against the image's own estimate,
        :func:`judge_against_own`: ``family_weight`` < 1 blends the own estimate in,
        ``gamma`` stays the identified one).

    Raises
    ------
    ValueError
        An image of another shape than the family's, a radius giving another patch size,
        bad bead positions, or no usable bead.
    """
    check_instance(subspace, OperatorSubspace, "subspace",
                   "Learn a family with estimate_subspace, or load one with "
                   "load_subspace; a single image's operator needs no identification.")
    max_iter = check_int(max_iter, "max_iter", minimum=1)
    img = as_image(image)
    if tuple(img.shape) != tuple(subspace.shape):
        raise ValueError(f"`image` has shape {tuple(img.shape)}, but the family was learnt "
                         f"on images of shape {tuple(subspace.shape)}: identify with a "
                         "family of this image size")
    r = float(psf_radius if psf_radius is not None
              else subspace.metadata.get("psf_radius", np.nan))
    if not (np.isfinite(r) and r > 0):
        raise ValueError(f"`psf_radius` must be a positive number of pixels (the family "
                         f"does not record one), got {psf_radius!r}")
    found = image_patches(image, r, threshold=threshold, positions=beads)
    if found.patches is None:
        raise ValueError(f"no usable bead in `image` to identify its operator: "
                         f"{found.summary}")
    patches = found.patches
    size = subspace.basis.shape[1]
    if patches.psf.shape[1] != size:
        raise ValueError(f"`psf_radius` = {r:g} px gives {patches.psf.shape[1]} px patches; "
                         f"the family's PSFs are {size} px: use the family's radius "
                         f"({subspace.metadata.get('psf_radius')})")
    c = _coefficients(patches.psf, subspace.basis)  # (P, I)
    at = space_at(subspace.space, subspace.grid, patches.centers)  # (P, J)
    sd = patches.noise / patches.flux  # per-pixel noise of the sum-1 patches
    gamma, lam, g, history = identify_gamma(c, at, subspace.gammas, prior=prior, sd=sd,
                                            amplitude_range=amplitude_range,
                                            max_iter=max_iter, affine=affine_maps(subspace),
                                            slopes=slope_frame(subspace, patches.centers))
    if not prior and not lam.any():
        raise ValueError("the beads' PSFs lie outside the family's cone (every weight is "
                         "0): is this image from the same microscope and PSF radius?")
    op = subspace.operator_from(gamma, project=False)
    fit = heldout_residuals(op, patches)  # on the beads it was identified from
    sure = resample(patches, c, at, subspace, prior=prior, sd=sd,
                    amplitude_range=amplitude_range, max_iter=max_iter)
    model_error = median_beyond_noise(fit.residual, fit.noise_floor)
    warning = None
    bound = warn_bound(subspace)
    if model_error > bound:
        warning = (f"the family does not explain the clicked beads: its operator misses "
                   f"them by {model_error:.2f} of their PSF beyond their noise (bound "
                   f"{bound:.2g}, from the family's error on its own held-out beads); it "
                   "may be far from this image's (a condition the family did not learn, "
                   "another microscope, or beads that are not single points): click more "
                   "beads, or learn a family that covers this condition")
    per_bead = beyond_noise_each(fit.residual, fit.noise_floor)
    worst = int(np.argmax(per_bead))
    if model_error <= bound and per_bead[worst] > WARN_BEAD_RATIO * bound:
        y, x = patches.centers[worst]
        warning = (f"the family does not explain the clicked bead at ({y:.0f}, {x:.0f}): "
                   f"its operator misses it by {per_bead[worst]:.2f} of its PSF beyond its "
                   f"noise ({per_bead[worst] / bound:.1f}x the bound {bound:.2g}); the "
                   "operator may be far from this image's around it (a condition the "
                   "family did not learn there, or not a single bead): click more beads "
                   "around it, or learn a family that covers this condition")
    meta = {"identification": {
        "model_error": model_error,
        "residual_median": float(np.median(fit.residual)),
        "noise_floor_median": float(np.median(fit.noise_floor)),
        **sure, "warning": warning, "warning_bound": bound, "prior": bool(prior),
        "bead_model_errors": per_bead.tolist(),
        "gamma": gamma.tolist(), "weights": lam.tolist(),
        "positions": patches.centers.tolist(), "amplitudes": g.tolist(),
        "objective": history, "n_beads": int(len(c)), "n_space": subspace.n_space,
        "enough_beads": bool(len(c) >= subspace.n_space), "beads_table": found.summary}}
    # many beads: no worse than the image's own estimate from them (held-out judgement)
    choice = judge_against_own(patches, c, at, subspace, prior=prior, sd=sd,
                               amplitude_range=amplitude_range, max_iter=max_iter)
    meta["identification"]["choice"] = None if choice is None else choice.to_dict()
    if choice is not None and choice.weight < 1.0:
        own = own_estimate(patches, subspace.shape, grid_step=subspace.grid_step)
        if own is not None:
            op = blend(op, own, choice.weight)
    if warning:
        warnings.warn(warning, IdentificationWarning, stacklevel=2)
    return ProductConvolution(op.basis, op.coefficients, shape=op.shape, grid=op.grid,
                              metadata=meta)
