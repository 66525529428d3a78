"""Identify the operator of one blurred image from a few of its beads (paper, Appendix D).

A family of operators (:class:`~napari_psfspace.core.family.OperatorFamily`) holds the
operators of one microscope under the conditions it was learnt on. Those operators vary
with a few conditions (focus, a tilt of the slide), so an image's operator is identified
in the family's own few dimensions (:mod:`~napari_psfspace.core.family.dimensions`,
learnt with the family): its field is the family's mean plus ``L`` coordinates along the
family's principal directions, or, where the family's own images say it does better, a
point of the family's curve (:mod:`~napari_psfspace.core.family.curve`: one condition
at the centre and its slopes across the field), the family's miss beyond either kriged
from the beads' residuals. A handful of beads pins down those few numbers, where ``J``
spatial maps of ``I`` coefficients each would need many.

- Each clicked bead, centred and free of background, gives its coefficients on the
  family's PSF basis; the coordinates and the beads' amplitudes are fitted by
  alternating exact least squares (:func:`~napari_psfspace.core.family.coordinates.
  fit_coordinates`; on a curve, by Gauss-Newton, :meth:`~napari_psfspace.core.family.
  curve.Curve.fit`), the coordinates with the family's spread of them as their prior.
- Each bead is judged left out (:mod:`.bead_check`); one that disagrees with the others
  (an unresolved pair, a saturated bead, one on a structure) is left out, and said so.
- The spread of the PSF over the field (the posterior standard deviation, relative to
  its norm) gives the place where one more bead would help most, and an error band
  calibrated on the family's own images (:mod:`.identify_report`).
- With many beads the identified operator is judged against the image's own estimate on
  held-out beads and kept no worse than it (:func:`judge_against_own`).

``prior=False`` is the paper's identification: ``Gamma`` in the cone of the ``Gamma_k``
(:mod:`.cone_identify`).
"""

from __future__ import annotations

import warnings

import numpy as np

from ..beads.window import bump_window
from ..common.deprecate import renamed_keyword
from ..common.spacing import partial_border
from ..common.threads import blas_threads
from ..common.validate import as_image, check_instance, check_int
from ..family.choice import PRIOR_WEIGHT, Choice, blend, choose_between, own_estimate
from ..family.curve import Curve, identify_any
from ..family.dimensions import family_fields, family_model
from ..family.patches import image_patches
from ..family.result import OperatorFamily, space_at
from ..model.cone import Cone, reduce_cone
from ..model.estimate import ESTIMATE_IMAGES
from ..model.field import assemble_operator
from ..model.heldout import (
    beyond_noise_each,
    heldout_residuals,
    median_beyond_noise,
    split_holdout,
)
from ..model.operator import ProductConvolution
from .bead_check import check_beads, shape_scores
from .cone_identify import AMPLITUDE_RANGE, identify_gamma, solve_identification
from .identify_report import (
    IdentificationWarning,
    error_band,
    family_model_error,
    left_out_warning,
    miss_warning,
    more_beads_text,
    spread_warning,
    warn_bound,
)

__all__ = ["AMPLITUDE_RANGE", "IdentificationWarning", "MIN_BEADS_JUDGED", "coefficients_on",
           "family_model_error", "field_operator", "identify_operator", "judge_against_own",
           "solve_identification", "warn_bound"]


def coefficients_on(psf: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Least-squares coefficients (P, I) of patches (P, S, S) on the basis (I, S, S) (the
    refitted basis images are not exactly orthonormal)."""
    b = basis.reshape(len(basis), -1)
    return np.linalg.lstsq(b.T, psf.reshape(len(psf), -1).T, rcond=None)[0].T


def field_operator(family: OperatorFamily, field: np.ndarray, c: np.ndarray, *,
                   at: np.ndarray | None = None) -> ProductConvolution:
    """The operator of a coefficient field (G, I) at the family's nodes, its PSFs kept in
    the cone of the family's observed PSFs and the clicked beads' (``c``, (P, I), their
    reduced cone: at most 20 more generators);
    ``at``: only right at these positions (as :func:`~..model.field.assemble_operator`)."""
    gens = np.vstack([family.cone.generators, reduce_cone(c).generators])
    op, _ = assemble_operator(family.basis, gens, lambda nodes: field, family.shape,
                              grid_step=family.grid_step, cone=Cone(gens), at=at,
                              constraint="cone")
    return op


def _identify(family, c, centers, sd, *, prior: bool, amplitude_range, max_iter, at=None):
    """The operator identified from beads, and how: the few dimensions' ``(field,
    spread, fit)``, or the paper's cone's ``(gamma, weights, amplitudes, objective)``."""
    if not prior:
        space = space_at(family.space, family.grid, centers)
        found = identify_gamma(c, space, family.gammas, amplitude_range=amplitude_range,
                               max_iter=max_iter)
        field = family.maps(found[0]).reshape(family.n_psf, -1).T
        if at is None:
            return family.operator_from(found[0], project=False), found
        op, _ = assemble_operator(family.basis, family.cone.generators,
                                  lambda nodes: field, family.shape,
                                  grid_step=family.grid_step, cone=family.cone, at=at,
                                  constraint="cone")
        return op, found
    _, found = identify_any(family_model(family), c, sd, centers,
                            amplitude_range=amplitude_range, spread=at is None)
    return field_operator(family, found[0], c, at=at), found


#: Fewest usable beads at which the identified operator is judged against the image's own
#: estimate on held-out beads (a fifth of them): with as many, the image's own estimate
#: is a real alternative, and the identification is kept no worse than it (blended with
#: it, or replaced, as the family's images are: :mod:`~napari_psfspace.core.family.
#: choice`).
MIN_BEADS_JUDGED = 15


def judged_prior(family: OperatorFamily, n_beads: int) -> float:
    """The family's weight the judgement leans to among those its held-out beads cannot
    tell apart (:func:`~napari_psfspace.core.family.choice.pick_weight`'s ``prior``),
    for an image of ``n_beads`` usable beads.

    An image with as many beads as the family's images have (their median) leans as they
    do, to the even blend (:data:`~napari_psfspace.core.family.choice.PRIOR_WEIGHT`):
    its own estimate is as good as theirs. With fewer, its own estimate is learnt from
    fewer beads, and it leans to the identified operator by the square of its share of
    the typical count, to it alone with none. The square, not the share: an own
    estimate's field error grows faster than the inverse of its bead count as its beads
    thin (the thin-plate fields interpolate across wider gaps, beside the noise), and a
    few held-out beads that cannot tell a blend from the identified operator should
    then keep the latter rather than bring in part of an own estimate from a few dozen
    beads (``bench/bench_identify_curve.py``, 40 beads).
    """
    counts = family.metadata.get("beads_per_image") or []
    typical = float(np.median(counts)) if len(counts) else float(n_beads)
    share = min(1.0, float(n_beads) / max(typical, 1.0))
    return 1.0 - (1.0 - PRIOR_WEIGHT) * share ** 2


def judge_against_own(patches, c: np.ndarray, family: OperatorFamily, *,
                      prior: bool = True, sd: np.ndarray | None = None,
                      amplitude_range=AMPLITUDE_RANGE, max_iter: int = 100
                      ) -> Choice | None:
    """The family's weight against the image's own estimate, on held-out beads.

    About a fifth of the beads, spread over the field, are held out; the operator
    identified from the others and the image's own estimate from the same others
    (:func:`~napari_psfspace.core.family.choice.own_estimate`) are blended at each
    weight and judged on them (:func:`~napari_psfspace.core.family.choice.
    choose_between`). None below :data:`MIN_BEADS_JUDGED` beads.
    """
    if len(c) < MIN_BEADS_JUDGED:
        return None
    mask = split_holdout(patches.centers, family.shape)
    if not mask.any() or mask.all():
        return None
    held = patches.subset(mask)
    sd = np.ones(len(c)) if sd is None else np.asarray(sd, np.float64)
    op, _ = _identify(family, c[~mask], patches.centers[~mask], sd[~mask], prior=prior,
                      amplitude_range=amplitude_range, max_iter=max_iter, at=held.centers)
    own = own_estimate(patches.subset(~mask), family.shape, grid_step=family.grid_step,
                       n_image=len(c), at=held.centers)
    return choose_between(_psfs(op, held.centers), own, held,
                          prior=judged_prior(family, len(c)))


def _psfs(op: ProductConvolution, points: np.ndarray) -> np.ndarray:
    return np.array([op.psf_at(y, x) for y, x in np.asarray(points).reshape(-1, 2)])


def _image_weights(family: OperatorFamily, field: np.ndarray) -> np.ndarray:
    """The weights (K,) of the family's images whose fields mix into ``field`` (G, I), the
    model's field without the miss (least squares through the images' deviations from
    their mean: exact for the lines, whose directions are combinations of them)."""
    fields = family_fields(family.space, family.gammas)
    mean = fields.mean(axis=0)
    dev = (fields - mean).reshape(family.n_images, -1)
    u = np.linalg.lstsq(dev.T, (np.asarray(field) - mean).reshape(-1), rcond=None)[0]
    return 1.0 / family.n_images + u


def _few_dimensions(family, found, c, centers, amplitude_range) -> dict:
    """The identification's own figures: coordinates, amplitudes, spread, band."""
    field, spread, fit = found
    model = family_model(family)
    nodes = model.nodes
    gamma = np.linalg.lstsq(family.space.reshape(family.n_space, -1).T, field,
                            rcond=None)[0].T
    inside = model.central
    predicted = float(np.sqrt(np.mean(spread[inside] ** 2)))
    band = error_band(family, predicted)
    where = nodes[inside][int(np.argmax(spread[inside]))]
    if isinstance(model, Curve):
        # the condition at the centre, and its change across the field along rows and
        # along columns
        theta = model.theta(fit.z)
        coords, slopes, n_planar = theta[:1], theta[1:].reshape(1, 2), 1
        bare = model.field(fit.z)
    else:
        n_planar = int((family.metadata.get("dimensions") or {}).get("n_planar") or 0)
        n_const = len(fit.z) - 2 * n_planar
        coords = fit.z[:n_const]
        slopes = fit.z[n_const:].reshape(2, n_planar).T  # each planar coordinate's
        bare = model.field(coords)
    return {"gamma": gamma, "weights": _image_weights(family, bare),
            "coordinates": coords.tolist(), "n_directions": len(coords),
            "slopes": slopes.tolist(), "n_planar": n_planar,
            "kind": "curve" if isinstance(model, Curve) else "lines",
            "amplitudes": fit.amplitudes, "objective": [],
            "psf_spread": float(np.mean(spread)), "psf_spread_max": float(np.max(spread)),
            "psf_spread_where": where.tolist(), "error_predicted": predicted,
            "error_band": None if band is None else list(band),
            "more_beads_at": where.tolist()}


def _paper(family, found, c) -> dict:
    gamma, lam, g, history = found
    if not lam.any():
        raise ValueError("the beads' PSFs lie outside the family's cone (every weight "
                         "is 0): is this image from the same microscope and PSF radius?")
    return {"gamma": gamma, "weights": lam, "coordinates": None, "n_directions": None,
            "slopes": None, "n_planar": None, "kind": "cone",
            "amplitudes": g, "objective": history, "psf_spread": None,
            "psf_spread_max": None, "psf_spread_where": None, "error_predicted": None,
            "error_band": None, "more_beads_at": None}


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
    """The operator of the family that explains the beads of one image.

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
        Alternations at most of the paper's identification (``prior=False``).
    prior : bool
        The family's few dimensions with its spread as their prior (default; see the
        module's notes). ``False``: the paper's hard constraint, ``Gamma`` in the cone
        of the ``Gamma_k``.

    Returns
    -------
    ProductConvolution
        Its PSFs sum to 1 and lie in the cone of the family's observed PSFs and the
        beads' (or, blended with the image's own estimate, between the two).
        ``metadata["identification"]`` holds ``gamma`` (I, J: the field on the family's
        spatial basis), ``weights`` (K,: the family's images mixed in, or the cone's),
        ``kind`` (``"lines"``, ``"curve"`` or ``"cone"``), ``coordinates`` (L,) and
        ``n_directions``, ``slopes`` (M, 2: how the first ``M`` coordinates change from
        one side of the field to the other along rows and columns; a curve's: its
        condition at the centre, and its change across rows and columns, in the family's
        units of it) and ``n_planar``, the beads' ``positions`` and
        ``amplitudes``, ``n_beads``, ``left_out`` (the clicked beads left out, with
        their ``score`` and ``shape``: :mod:`.bead_check`), every given bead's
        ``scores`` and ``shapes``, how well the operator fits the beads it
        kept (the median relative residual of their patches, its noise floor, and
        ``model_error = sqrt(median residual^2 - median floor^2)``, the relative error
        beyond the noise, which :func:`~napari_psfspace.core.restore.deconvolve.deblur`
        allows for); its spread (``psf_spread``: the posterior standard deviation of
        the PSF relative to its norm, mean over the field; ``psf_spread_max`` and
        ``psf_spread_where``), ``error_predicted`` (the rms spread) and ``error_band``
        (the 90 % band of the PSF error over the field, :func:`~.identify_report.
        error_band`), ``more_beads_at`` (where one more bead would help most);
        ``warning`` (None, or why, naming that place; an :class:`IdentificationWarning`
        is issued too) and ``prior``; ``choice`` (None below :data:`MIN_BEADS_JUDGED`
        beads; else the held-out judgement against the image's own estimate,
        :func:`judge_against_own`: ``family_weight`` < 1 blends the own estimate in,
        ``gamma`` stays the identified one).

    Raises
    ------
    ValueError
        An image of another shape than the family's, a radius giving another patch size,
        bad bead positions, or no usable bead.
    """
    max_iter, found_beads, patches = _patches(image, family, beads, psf_radius, threshold,
                                              max_iter)
    c, sd, scores, left, shapes, patches = _checked_beads(family, amplitude_range, prior, patches)
    op, found = _identify(family, c, patches.centers, sd, prior=prior,
                          amplitude_range=amplitude_range, max_iter=max_iter)
    own = (_few_dimensions(family, found, c, patches.centers, amplitude_range) if prior
           else _paper(family, found, c))
    warning, meta = _record(family, prior, found_beads, patches, c, scores, left, shapes, op, own)
    # many beads: no worse than the image's own estimate from them (held-out judgement)
    choice = judge_against_own(patches, c, family, prior=prior, sd=sd,
                               amplitude_range=amplitude_range, max_iter=max_iter)
    meta["identification"]["choice"] = None if choice is None else choice.to_dict()
    if choice is not None and choice.weight < 1.0:
        own_op = own_estimate(patches, family.shape, grid_step=family.grid_step)
        if own_op is not None:
            op = blend(op, own_op, choice.weight)
    if warning:
        warnings.warn(warning, IdentificationWarning, stacklevel=2)
    return ProductConvolution(op.basis, op.coefficients, shape=op.image_shape, grid=op.grid,
                              metadata=meta)


def _patches(image, family, beads, psf_radius, threshold, max_iter):
    """The image's bead patches at the family's patch size; one clear line for a bad value,
    another shape or no usable bead."""
    check_instance(family, OperatorFamily, "family",
                   "Learn a family with estimate_family, or load one with "
                   "load_family; a single image's operator needs no identification.")
    max_iter = check_int(max_iter, "max_iter", minimum=1)
    img = as_image(image, copies=ESTIMATE_IMAGES)  # its beads found and cut as estimated
    if tuple(img.shape) != tuple(family.shape):
        raise ValueError(f"`image` has shape {tuple(img.shape)}, but the family was learnt "
                         f"on images of shape {tuple(family.shape)}: identify with a "
                         "family of this image size")
    r = float(psf_radius if psf_radius is not None
              else family.metadata.get("psf_radius", np.nan))
    if not (np.isfinite(r) and r > 0):
        raise ValueError(f"`psf_radius` must be a positive number of pixels (the family "
                         f"does not record one), got {psf_radius!r}")
    found_beads = image_patches(image, r, threshold=threshold, positions=beads,
                                border=partial_border(r))
    if found_beads.patches is None:
        raise ValueError(f"no usable bead in `image` to identify its operator: "
                         f"{found_beads.summary}")
    patches = found_beads.patches
    size = family.basis.shape[1]
    if patches.psf.shape[1] != size:
        raise ValueError(f"`psf_radius` = {r:g} px gives {patches.psf.shape[1]} px patches; "
                         f"the family's PSFs are {size} px: use the family's radius "
                         f"({family.metadata.get('psf_radius')})")
    return max_iter, found_beads, patches


def _checked_beads(family, amplitude_range, prior, patches):
    """The beads' coefficients on the family's basis and their noise; with the prior, the
    beads the family cannot explain left out (:mod:`.bead_check`) and the noise as the
    family measured it on its own beads (its shot noise, centring and background beyond the
    background's noise)."""
    c = coefficients_on(patches.psf, family.basis)  # (P, I)
    sd = patches.noise / patches.flux  # per-pixel noise of the sum-1 patches
    left, scores = [], np.full(len(c), np.nan)
    shapes = shape_scores(patches.psf, c, family.basis, patches.noise / patches.flux,
                          bump_window(patches.size, patches.r, patches.r_ext))
    if prior:
        check = check_beads(family_model(family), c, sd, patches.centers, shapes=shapes,
                            amplitude_range=amplitude_range)
        left, scores = check.left_out, check.scores
        if left:
            patches, c, sd = patches.subset(check.keep), c[check.keep], sd[check.keep]
        # a bead's noise as the family measured it on its own beads (its shot noise,
        # centring and background beyond the background's noise; the check above keeps
        # the yardstick it was calibrated with)
        sd = sd * float((family.metadata.get("dimensions") or {}).get("noise_factor", 1.0))
    return c, sd, scores, left, shapes, patches


def _record(family, prior, found_beads, patches, c, scores, left, shapes, op, own):
    """The identification's record: how well the operator fits the beads it kept, its spread
    and where one more bead would help, the beads left out and the warning (None, or why)."""
    fit = heldout_residuals(op, patches)  # on the beads it was identified from
    model_error = median_beyond_noise(fit.residual, fit.noise_floor)
    bound = warn_bound(family)
    every = found_beads.patches.centers
    notes = [miss_warning(model_error, bound),
             left_out_warning(every[left], scores[left]),
             None if not prior else spread_warning(
                 None if own["error_band"] is None else tuple(own["error_band"]),
                 own["psf_spread"], bound)]
    warning = "; ".join(n for n in notes if n) or None
    if warning and own["more_beads_at"] is not None:
        warning = f"{warning}; {more_beads_text(own['more_beads_at'])}"
    meta = {"identification": {
        "model_error": model_error,
        "residual_median": float(np.median(fit.residual)),
        "noise_floor_median": float(np.median(fit.noise_floor)),
        "warning": warning, "warning_bound": bound, "prior": bool(prior),
        "bead_model_errors": beyond_noise_each(fit.residual, fit.noise_floor).tolist(),
        **{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in own.items()},
        "positions": patches.centers.tolist(),
        "left_out": [{"position": every[i].tolist(), "score": float(scores[i]),
                      "shape": float(shapes[i])} for i in left],
        "scores": [None if not np.isfinite(s) else float(s) for s in scores],
        "shapes": shapes.tolist(),
        "n_beads": int(len(c)), "n_space": family.n_space,
        "enough_beads": bool(len(c) >= 5), "beads_table": found_beads.summary}}
    return warning, meta
