"""Identify the operator of one blurred image from a few of its beads (paper, Appendix D).

A family of operators (:class:`~napari_psfspace.core.family.OperatorFamily`) is known:
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

By default (``prior=True``) the family is a Gaussian prior rather than a hard constraint
(:mod:`.posterior`): a condition between those learnt is rarely a non-negative mix of
them, and one outside them is none. The family's fields give the prior's mean and
covariance (conditions continuous: any mix of the learnt ones, beyond their range too,
weights varying over the field, and fields the family never showed); the clicked beads
give the likelihood; the scales of each part are those of highest evidence. The
operator is the posterior mean field, reported with its spread (the posterior standard
deviation of the PSF over the field), and a warning (:class:`IdentificationWarning`,
``metadata["identification"]["warning"]``) says when the operator misses the clicked
beads (or one of them) beyond their noise, or when they leave part of the field
undetermined, and where more beads would help.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import nnls

from ..common.deprecate import renamed_keyword
from ..common.spacing import partial_border
from ..common.threads import blas_threads
from ..common.validate import as_image, check_instance, check_int
from ..family.choice import Choice, blend, choose_between, own_estimate
from ..family.patches import image_patches
from ..family.result import OperatorFamily, space_at
from ..model.cone import Cone, reduce_cone
from ..model.field import assemble_operator
from ..model.heldout import (
    beyond_noise,
    beyond_noise_each,
    heldout_residuals,
    median_beyond_noise,
    residuals_of,
    split_holdout,
)
from ..model.operator import ProductConvolution
from .posterior import FieldPrior, Posterior, bilinear, family_prior, posterior_field

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
                         max_iter: int = 100, tol: float = 1e-8
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
        lam, _ = nnls(m_mat, c.ravel(), maxiter=50 * n_k)
        m = np.tensordot(lam, v, axes=1)  # (P, I)
        mm = (m * m).sum(axis=1)
        g = np.where(mm > 0, (m * c).sum(axis=1) / np.maximum(mm, 1e-300), 1.0).clip(a, b)
        history.append(0.5 * float(((g[:, None] * m - c) ** 2).sum()))
        if len(history) > 1 and abs(history[-2] - history[-1]) <= tol * max(history[-2],
                                                                           1e-300):
            break
    return lam, g, history


#: Folds of the resampling over the beads (leave-one-bead-out below this count).
N_FOLDS = 5
#: The warning's bound on the identified operator's error on the clicked beads, beyond
#: their noise (relative l2 of the PSF; ``model_error``, measured on the beads it was
#: fitted to), in units of the family's own error on beads it never saw (the median
#: over its images of the same measure on their held-out beads). The bound separates,
#: on wide focus series, the images whose operator is more than twice as far from the
#: truth as one estimated from all their beads from the others, and passes the measured
#: stacks (``bench/bench_identify_wide.py``, bench/RESULTS.md@9b74991).
WARN_RATIO = 1.1
#: The bound without held-out figures (a family learnt with ``holdout=None``), and its
#: floor otherwise.
WARN_MODEL_ERROR = 0.1
WARN_FLOOR = 0.03
#: The warning's bound on the worst clicked bead, in units of ``warning_bound``: the
#: median (``model_error``) hides one bead of five that the family cannot explain (a
#: corner of a tilted field beyond the focus learnt: its PSF a third outside the
#: family's PSF basis; an unresolved pair). Set above the worst bead of 5 on all but a
#: few images of wide focus series (``bench/bench_identify_wide.py``; bench/RESULTS.md@9b74991).
WARN_BEAD_RATIO = 4.0


def family_model_error(subspace: OperatorFamily) -> float | None:
    """The family's error beyond the noise on beads it never saw: the median over its
    images of ``sqrt(residual^2 - floor^2)`` of their held-out beads (None without)."""
    held = [h for h in subspace.metadata.get("heldout") or []
            if h.get("n_beads") and h.get("residual_mean") is not None]
    if not held:
        return None
    return float(np.median([beyond_noise(h["residual_mean"], h["noise_floor_mean"])
                            for h in held]))


def warn_bound(subspace: OperatorFamily) -> float:
    """The ``model_error`` above which :func:`identify_operator` warns."""
    ref = family_model_error(subspace)
    return WARN_MODEL_ERROR if ref is None else max(WARN_FLOOR, WARN_RATIO * ref)


def identify_gamma(c: np.ndarray, at: np.ndarray, gammas: np.ndarray, *,
                   amplitude_range=AMPLITUDE_RANGE, max_iter: int = 100
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """The paper's problem (9): ``Gamma`` (I, J) in the cone of the ``Gamma_k`` that
    explains the beads' coefficients ``c`` (P, I) at their spatial basis values ``at``
    (P, J).

    Returns
    -------
    gamma : ndarray of shape (I, J)
    weights : ndarray of shape (K,)
    amplitudes : ndarray of shape (P,)
    objective : list of float
    """
    v = np.einsum("pj,kij->kpi", at, gammas)  # (K, P, I)
    lam, g, history = solve_identification(c, v, amplitude_range=amplitude_range,
                                           max_iter=max_iter)
    return np.tensordot(lam, gammas, axes=1), lam, g, history


#: Most bead coefficients (beads x I) the posterior is computed from; beyond, a subset of
#: the beads spread over the field (with that many beads the image's own estimate is
#: judged against it anyway, :func:`judge_against_own`).
MAX_OBSERVATIONS = 600
#: Most beads the prior's scales are chosen from (a subset spread over the field).
MAX_EVIDENCE_BEADS = 8


def spread_subset(centers: np.ndarray, n: int) -> np.ndarray:
    """Indices of at most ``n`` of ``centers`` (P, 2) spread over the field: farthest
    points, from the one nearest their mean."""
    pts = np.asarray(centers, np.float64).reshape(-1, 2)
    if len(pts) <= n:
        return np.arange(len(pts))
    picks = [int(np.argmin(np.hypot(*(pts - pts.mean(axis=0)).T)))]
    d = np.hypot(*(pts - pts[picks[0]]).T)
    while len(picks) < n:
        nxt = int(np.argmax(d))
        picks.append(nxt)
        d = np.minimum(d, np.hypot(*(pts - pts[nxt]).T))
    return np.sort(np.array(picks))


def posterior_of(subspace: OperatorFamily, c: np.ndarray, centers: np.ndarray,
                 sd: np.ndarray, *, amplitude_range=AMPLITUDE_RANGE,
                 prior: FieldPrior | None = None,
                 log_scales: np.ndarray | None = None, spread: bool = True) -> Posterior:
    """The posterior of the field of beads' coefficients ``c`` (P, I) at ``centers``
    (P, 2) with noise ``sd`` (P,) under the family's prior (:func:`~.posterior.
    posterior_field`), its scales chosen on at most :data:`MAX_EVIDENCE_BEADS` beads and
    the field on at most :data:`MAX_OBSERVATIONS` coefficients."""
    prior = family_prior(subspace) if prior is None else prior
    kw = {"amplitude_range": amplitude_range, "psfs": subspace.basis}
    if log_scales is None and len(c) > MAX_EVIDENCE_BEADS:
        keep = spread_subset(centers, MAX_EVIDENCE_BEADS)
        log_scales = posterior_field(prior, c[keep], centers[keep], sd[keep],
                                     **kw).log_scales
    keep = spread_subset(centers, max(1, MAX_OBSERVATIONS // c.shape[1]))
    return posterior_field(prior, c[keep], centers[keep], sd[keep], log_scales=log_scales,
                           spread=spread, **kw)


def field_operator(subspace: OperatorFamily, field: np.ndarray, c: np.ndarray, *,
                   at: np.ndarray | None = None) -> ProductConvolution:
    """The operator of a coefficient field (G, I) at the family's nodes, its PSFs kept in
    the cone of the family's observed PSFs and the clicked beads' (``c``, (P, I), their
    reduced cone: at most 20 more generators);
    ``at``: only right at these positions (as :func:`~..model.field.assemble_operator`)."""
    gens = np.vstack([subspace.cone.generators, reduce_cone(c).generators])
    op, _ = assemble_operator(subspace.basis, gens, lambda nodes: field, subspace.shape,
                              grid_step=subspace.grid_step, cone=Cone(gens), at=at,
                              constraint="cone")
    return op


def _identify(subspace, c, centers, sd, *, prior: bool, amplitude_range, max_iter,
              at=None, field_prior=None, log_scales=None):
    """The operator identified from beads (the posterior's, or the paper's cone), with
    the posterior (None for the paper's) and the cone's ``(gamma, weights, amplitudes,
    objective)``."""
    if not prior:
        space = space_at(subspace.space, subspace.grid, centers)
        found = identify_gamma(c, space, subspace.gammas, amplitude_range=amplitude_range,
                               max_iter=max_iter)
        if at is None:
            return subspace.operator_from(found[0], project=False), None, found
        field = subspace.maps(found[0]).reshape(subspace.n_psf, -1).T
        op, _ = assemble_operator(subspace.basis, subspace.cone.generators,
                                  lambda nodes: field, subspace.shape,
                                  grid_step=subspace.grid_step, cone=subspace.cone, at=at,
                                  constraint="cone")
        return op, None, found
    post = posterior_of(subspace, c, centers, sd, amplitude_range=amplitude_range,
                        prior=field_prior, log_scales=log_scales, spread=at is None)
    return field_operator(subspace, post.mean, c, at=at), post, None


#: Fewest usable beads at which the identified operator is judged against the image's own
#: estimate on held-out beads (a fifth of them): with as many, the image's own estimate
#: is a real alternative, and the identification is kept no worse than it (blended with
#: it, or replaced, as the family's images are: :mod:`~napari_psfspace.core.family.
#: choice`). From all of an image's beads the identified operator could be worse than
#: ``estimate_operator`` on wide focus series (``bench/bench_identify_wide.py``, column
#: ``all``; bench/RESULTS.md@9b74991).
MIN_BEADS_JUDGED = 15


def judge_against_own(patches, c: np.ndarray, subspace: OperatorFamily, *,
                      prior: bool = True, sd: np.ndarray | None = None,
                      amplitude_range=AMPLITUDE_RANGE, max_iter: int = 100,
                      log_scales: np.ndarray | None = None) -> Choice | None:
    """The family's weight against the image's own estimate, on held-out beads.

    About a fifth of the beads, spread over the field, are held out; the operator
    identified from the others and the image's own estimate from the same others
    (:func:`~napari_psfspace.core.family.choice.own_estimate`) are blended at each
    weight and judged on them (:func:`~napari_psfspace.core.family.choice.
    choose_between`). None below :data:`MIN_BEADS_JUDGED` beads.
    """
    if len(c) < MIN_BEADS_JUDGED:
        return None
    mask = split_holdout(patches.centers, subspace.shape)
    if not mask.any() or mask.all():
        return None
    held = patches.subset(mask)
    op, *_ = _identify(subspace, c[~mask], patches.centers[~mask], _noise(sd, c)[~mask],
                       prior=prior, amplitude_range=amplitude_range, max_iter=max_iter,
                       at=held.centers, log_scales=log_scales)
    own = own_estimate(patches.subset(~mask), subspace.shape, grid_step=subspace.grid_step,
                       n_image=len(c))
    return choose_between(_psfs(op, held.centers), own, held)


def _noise(sd: np.ndarray | None, c: np.ndarray) -> np.ndarray:
    return np.ones(len(c)) if sd is None else np.asarray(sd, np.float64)


def _psfs(op: ProductConvolution, points: np.ndarray) -> np.ndarray:
    return np.array([op.psf_at(y, x) for y, x in np.asarray(points).reshape(-1, 2)])


class IdentificationWarning(UserWarning):
    """The family does not explain the beads an operator was identified from, or they
    leave part of the field undetermined."""


def resample(patches, c: np.ndarray, subspace: OperatorFamily, *,
             prior: bool = True, sd: np.ndarray | None = None,
             amplitude_range=AMPLITUDE_RANGE, max_iter: int = 100, n_folds: int = N_FOLDS,
             n_grid: int = 4, log_scales: np.ndarray | None = None) -> dict:
    """How the identification does on beads it did not see.

    Each fold of the beads (one bead each below ``n_folds`` beads) is predicted by the
    operator identified from the others (with the prior's scales ``log_scales``, those
    chosen from every bead, when given).

    Returns
    -------
    dict
        ``cv_residual_median`` and ``cv_noise_floor_median`` (the left-out beads'
        relative residuals and their noise), ``cv_model_error`` (``sqrt(median
        residual^2 - median floor^2)``: the error of the operator on beads it did not
        see, beyond their noise; None below 3 beads), ``cv_bead_model_errors`` (each
        bead's, when left out), ``jackknife_spread`` (the
        jackknife standard deviation of the PSFs over the folds at an ``n_grid x
        n_grid`` grid of the field, relative to their norm, averaged; None below 3
        beads), ``n_folds``.
    """
    n_p = len(c)
    if n_p < 3:
        return {"cv_residual_median": None, "cv_noise_floor_median": None,
                "cv_model_error": None, "cv_bead_model_errors": None,
                "jackknife_spread": None, "n_folds": 0}
    folds = np.arange(n_p) % min(int(n_folds), n_p)
    h, w = subspace.shape
    grid = np.stack(np.meshgrid((np.arange(n_grid) + 0.5) * h / n_grid,
                                (np.arange(n_grid) + 0.5) * w / n_grid, indexing="ij"),
                    axis=-1).reshape(-1, 2)
    res, floor, psfs = np.empty(n_p), np.empty(n_p), []
    sd = _noise(sd, c)
    field_prior = family_prior(subspace) if prior else None
    for f in np.unique(folds):
        out = folds == f
        left = patches.subset(out)
        op, *_ = _identify(subspace, c[~out], patches.centers[~out], sd[~out], prior=prior,
                           amplitude_range=amplitude_range, max_iter=max_iter,
                           at=np.vstack([left.centers, grid]), field_prior=field_prior,
                           log_scales=log_scales)
        r = residuals_of(_psfs(op, left.centers), left)
        res[out], floor[out] = r.residual, r.noise_floor
        psfs.append(_psfs(op, grid))
    psfs = np.array(psfs)  # (F, G, P, P)
    n_f = len(psfs)
    dev = psfs - psfs.mean(axis=0)
    var = (n_f - 1) / n_f * (dev ** 2).sum(axis=(0, 2, 3))  # jackknife, per position
    spread = np.sqrt(var) / np.linalg.norm(psfs.mean(axis=0), axis=(1, 2))
    return {"cv_residual_median": float(np.median(res)),
            "cv_noise_floor_median": float(np.median(floor)),
            "cv_model_error": median_beyond_noise(res, floor),
            "cv_bead_model_errors": beyond_noise_each(res, floor).tolist(),
            "jackknife_spread": float(spread.mean()), "n_folds": int(n_f)}


def miss_warning(model_error: float, per_bead: np.ndarray, centers: np.ndarray,
                 bound: float) -> str | None:
    """Why the family does not explain the clicked beads (None: it does): their median
    error beyond the noise above ``bound``, or one bead's above :data:`WARN_BEAD_RATIO`
    times it."""
    if model_error > bound:
        return (f"the family does not explain the clicked beads: its operator misses them "
                f"by {model_error:.2f} of their PSF beyond their noise (bound {bound:.2g}, "
                "from the family's error on its own held-out beads); it may be far from "
                "this image's (a condition the family did not learn, another microscope, "
                "or beads that are not single points): click more beads, or learn a "
                "family that covers this condition")
    worst = int(np.argmax(per_bead))
    if per_bead[worst] > WARN_BEAD_RATIO * bound:
        y, x = centers[worst]
        return (f"the family does not explain the clicked bead at ({y:.0f}, {x:.0f}): its "
                f"operator misses it by {per_bead[worst]:.2f} of its PSF beyond its noise "
                f"({per_bead[worst] / bound:.1f}x the bound {bound:.2g}); the operator may "
                "be far from this image's around it (a condition the family did not learn "
                "there, or not a single bead): click more beads around it, or learn a "
                "family that covers this condition")
    return None


#: The warning's bound on the posterior spread of the PSF (its mean over the field: on
#: wide focus series, within a third of the field error it predicts,
#: ``bench/bench_identify_wide.py``), in units of :func:`warn_bound` (the family's error
#: on its own held-out beads).
SPREAD_RATIO = 3.0


def least_determined(spread: np.ndarray, nodes: np.ndarray) -> str:
    """Where the posterior spread of the PSF (G,) is largest among the nodes (G, 2)."""
    y, x = nodes[int(np.argmax(spread))]
    return (f"the PSF is least determined around ({y:.0f}, {x:.0f}), off by up to "
            f"{float(np.max(spread)):.2f} of its norm: click beads there")


def spread_warning(spread: np.ndarray, nodes: np.ndarray, bound: float) -> str | None:
    """Why the clicked beads leave the operator undetermined (None: they do not): the
    mean posterior spread of the PSF (G,) at the nodes (G, 2) above
    :data:`SPREAD_RATIO` times ``bound``."""
    mean = float(np.mean(spread))
    if mean <= SPREAD_RATIO * bound:
        return None
    return (f"the clicked beads leave the operator undetermined: its PSF may be off by "
            f"{mean:.2f} of its norm on average over the field (bound "
            f"{SPREAD_RATIO * bound:.2g}, {SPREAD_RATIO:g}x the family's error on its own "
            "held-out beads)")


@renamed_keyword("subspace", "family")
@blas_threads
def identify_operator(
    image: np.ndarray,
    family: OperatorFamily,
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
    family : OperatorFamily
        The family of operators (:func:`~napari_psfspace.core.family.estimate_family`).
        ``subspace=`` is its deprecated name.
    beads : ndarray of shape (N, 2), optional
        Bead positions (row, column), pixels, e.g. a Points layer's; they are centred
        sub-pixel and checked (neighbours, saturation; a bead at least ``r`` from the
        edge is kept, its patch masked beyond it). Default: detected.
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
        The family as a Gaussian prior (default; see the module's notes): the operator
        is the posterior mean field given the beads (:mod:`.posterior`). ``False``: the
        paper's hard constraint, ``Gamma`` in the cone of the ``Gamma_k``.

    Returns
    -------
    ProductConvolution
        Its PSFs sum to 1 and lie in the cone of the family's observed PSFs and the
        beads' (or, blended with the image's own estimate, between the two).
        ``metadata["identification"]`` holds ``gamma`` (I, J: the field on the family's
        spatial basis), ``weights`` (K,: the posterior mean of the weights of the
        family's conditions, or the cone's), ``scales`` (the prior's, of highest
        evidence), the beads' ``positions`` and ``amplitudes``, ``n_beads``, and how well
        the operator fits those beads: the median relative residual of their patches,
        its noise floor, and ``model_error = sqrt(median residual^2 - median
        floor^2)``, the relative error of the operator beyond the noise (which
        :func:`~napari_psfspace.core.restore.deconvolve.deblur` allows for); its spread
        (``psf_spread``: the posterior standard deviation of the PSF relative to its
        norm, mean over the field; ``psf_spread_max`` and ``psf_spread_where``, the node
        where it is largest); how it does on beads left out (:func:`resample`:
        ``cv_model_error``, ``cv_bead_model_errors``, ...); ``warning`` (None, or why:
        the family does not explain the beads, ``model_error`` above
        ``warning_bound``, :func:`warn_bound`, or one of them, left out, by more than
        :data:`WARN_BEAD_RATIO` times that bound, or they leave the operator
        undetermined, :func:`spread_warning`; each says where more beads would help; an
        :class:`IdentificationWarning` is issued too) and ``prior``; ``choice`` (None
        below :data:`MIN_BEADS_JUDGED` beads; else the held-out judgement against the
        image's own estimate, :func:`judge_against_own`: ``family_weight`` < 1 blends
        the own estimate in, ``gamma`` stays the identified one).

    Raises
    ------
    ValueError
        An image of another shape than the family's, a radius giving another patch size,
        bad bead positions, or no usable bead.
    """
    subspace = family
    check_instance(family, OperatorFamily, "family",
                   "Learn a family with estimate_family, or load one with "
                   "load_family; a single image's operator needs no identification.")
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
    found = image_patches(image, r, threshold=threshold, positions=beads,
                          border=partial_border(r))
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
    sd = patches.noise / patches.flux  # per-pixel noise of the sum-1 patches
    op, post, paper = _identify(subspace, c, patches.centers, sd, prior=prior,
                                amplitude_range=amplitude_range, max_iter=max_iter)
    if paper is not None:
        gamma, lam, g, history = paper
        if not lam.any():
            raise ValueError("the beads' PSFs lie outside the family's cone (every weight "
                             "is 0): is this image from the same microscope and PSF radius?")
    fit = heldout_residuals(op, patches)  # on the beads it was identified from
    sure = resample(patches, c, subspace, prior=prior, sd=sd,
                    amplitude_range=amplitude_range, max_iter=max_iter,
                    log_scales=None if post is None else post.log_scales)
    model_error = median_beyond_noise(fit.residual, fit.noise_floor)
    bound = warn_bound(subspace)
    per_bead = beyond_noise_each(fit.residual, fit.noise_floor)
    # one bead the others cannot predict: the posterior bends towards any bead it is
    # given, so each is judged left out (the paper's cone cannot bend: as fitted)
    judged = per_bead if post is None or sure["cv_bead_model_errors"] is None else \
        np.asarray(sure["cv_bead_model_errors"])
    warning = miss_warning(model_error, judged, patches.centers, bound)
    if post is not None:
        nodes = family_prior(subspace).nodes
        gamma = np.linalg.lstsq(subspace.space.reshape(subspace.n_space, -1).T, post.mean,
                                rcond=None)[0].T
        # every bead's amplitude against the field (the posterior may use a subset)
        at_beads = bilinear(subspace.grid, patches.centers) @ post.mean
        mm = (at_beads * at_beads).sum(axis=1)
        g = np.where(mm > 0, (at_beads * c).sum(axis=1) / np.maximum(mm, 1e-300),
                     1.0).clip(*amplitude_range)
        lam, history = post.weights, []
        where = nodes[int(np.argmax(post.spread))]
        spread = {"psf_spread": float(np.mean(post.spread)),
                  "psf_spread_max": float(np.max(post.spread)),
                  "psf_spread_where": where.tolist(), "scales": post.scales}
        warning = warning or spread_warning(post.spread, nodes, bound)
        if warning:  # where more beads would help
            warning = f"{warning}; {least_determined(post.spread, nodes)}"
    else:
        spread = {"psf_spread": sure["jackknife_spread"], "psf_spread_max": None,
                  "psf_spread_where": None, "scales": None}
    meta = {"identification": {
        "model_error": model_error,
        "residual_median": float(np.median(fit.residual)),
        "noise_floor_median": float(np.median(fit.noise_floor)),
        **sure, **spread, "warning": warning, "warning_bound": bound,
        "prior": bool(prior),
        "bead_model_errors": per_bead.tolist(),
        "gamma": gamma.tolist(), "weights": lam.tolist(),
        "positions": patches.centers.tolist(), "amplitudes": g.tolist(),
        "objective": history, "n_beads": int(len(c)), "n_space": subspace.n_space,
        "enough_beads": bool(len(c) >= subspace.n_space), "beads_table": found.summary}}
    # many beads: no worse than the image's own estimate from them (held-out judgement)
    choice = judge_against_own(patches, c, subspace, prior=prior, sd=sd,
                               amplitude_range=amplitude_range, max_iter=max_iter,
                               log_scales=None if post is None else post.log_scales)
    meta["identification"]["choice"] = None if choice is None else choice.to_dict()
    if choice is not None and choice.weight < 1.0:
        own = own_estimate(patches, subspace.shape, grid_step=subspace.grid_step)
        if own is not None:
            op = blend(op, own, choice.weight)
    if warning:
        warnings.warn(warning, IdentificationWarning, stacklevel=2)
    return ProductConvolution(op.basis, op.coefficients, shape=op.shape, grid=op.grid,
                              metadata=meta)
