"""Each image's operator: the family's, its own estimate, or a blend, by held-out beads.

The family pools the beads of every image; with few or faint beads an image gains from
it, with many bright beads it may not (a shared basis and cone are a constraint its own
estimate does not have). The family acts as a prior: each image with enough beads gets
the blend ``w H_family + (1 - w) H_own`` of the family's operator and its own estimate
(PSFs ``w h_family + (1 - w) h_own``, still of sum 1) whose weight ``w`` in
:data:`WEIGHTS` best explains beads of its own that neither model saw (the held-out
split of :func:`~napari_psfspace.core.family.estimate.iter_estimate_family`; among
the weights those beads cannot tell apart, the one nearest :func:`prior_weight`: the
even blend where the image's beads determine its own field, leaning to the family where
they do not or where each bead is mostly noise; :func:`pick_weight`). ``w = 0`` is the
single-image estimate itself, so the family is never kept where the image's held-out
beads say its own estimate is better; ``w = 1`` is the paper's hard constraint.
Two estimates with partly independent errors do better blended than either alone (on
the wide focus series of ``bench_family_oracle.py``, their mean beats both on most
images).

An image keeps the family's operator where fewer than :data:`MIN_HELDOUT` of its beads
are held out or fewer than :data:`MIN_BEADS_OWN` train its own estimate (too few to
judge by; this is where the family is meant to help), and unless a blend explains its
held-out beads better than its own estimate beyond their scatter. Where those beads are
mostly noise (their median noise floor at the top of :data:`NOISE_FLOOR_RANGE` or above),
the other way round: the weight nearest the prior unless they show the own estimate
better beyond their scatter (:func:`pick_weight`'s ``faint``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..beads.patches import Patches
from ..beads.window import radial_distance
from ..model.fewbeads import FEW_BEADS, fit_few_beads
from ..model.heldout import HeldoutResiduals, noise_floors, residuals_of
from ..model.operator import ProductConvolution
from ..model.patch_fit import fit_patches

#: Fewest training beads for an image's own estimate to be a candidate (below, one
#: PSF for the field at most, and too few beads left to judge it by).
MIN_BEADS_OWN = 3
#: Fewest held-out beads to judge by.
MIN_HELDOUT = 3
#: The family's weights tried: 0 is the image's own estimate, 1 the family's operator.
WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)
#: Among the weights the held-out beads cannot tell from the best (and that beat the
#: image's own estimate), the one kept is the nearest to :func:`prior_weight`: this (the
#: even blend of two estimates with partly independent errors) for an image whose beads
#: determine its own field. Leaning to the family on every image (0.75, or from 0.5 to 1
#: with the noise's share of the held-out residuals) helps faint stacks but made one
#: image of a bright stack worse than its own estimate.
PRIOR_WEIGHT = 0.5
#: Per-bead noise (the held-out beads' median noise floor: their windowed noise's norm
#: over their windowed patch's) at and below which the prior weight is the share's
#: alone, and at and above which it is the family's operator (1); linear between. Where
#: one bead is mostly noise the image's own estimate is mostly noise too, whatever the
#: empirical Bayes share says of its departure from the family's mean. Set on a photon
#: sweep of both generators ("the prior weight from the beads' noise");
#: ranges from (0.2, 0.9) to (0.3, 0.8) gave nearly the same errors there.
NOISE_FLOOR_RANGE = (0.25, 0.85)


def prior_weight(share: float, floor: float = 0.0) -> float:
    """The family's weight a blend leans to, from the image's share of its own field
    and its beads' noise.

    ``share`` (:meth:`~napari_psfspace.core.family.shrink.Fields.share`, in [0, 1]) is
    how much of its departure from the family's mean field the image's own beads
    determine (empirical Bayes: its departure's spread over the family against its
    noise). Where they determine it (bright or many beads, ``share`` 1) the even blend
    :data:`PRIOR_WEIGHT`; where they determine none of it (``share`` 0) its own estimate
    is mostly noise, and the family's operator (1); linear between.

    ``floor`` (the median noise floor of the image's held-out beads, 0: noise-free, 1:
    all noise) leans further to the family: the even blend at or below the low end of
    :data:`NOISE_FLOOR_RANGE`, the family's operator at or above its high end. The
    larger of the two weights is kept. Faint beads can carry departures from the
    family's mean that are consistent over an image's beads, so that the share stays
    high, but do not bring its PSFs closer to the truth.
    """
    s = float(np.clip(share, 0.0, 1.0)) if np.isfinite(share) else 1.0
    lo, hi = NOISE_FLOOR_RANGE
    f = float(np.clip((floor - lo) / (hi - lo), 0.0, 1.0)) if np.isfinite(floor) else 0.0
    return max(1.0 - (1.0 - PRIOR_WEIGHT) * s, PRIOR_WEIGHT + (1.0 - PRIOR_WEIGHT) * f)


def own_estimate(patches: Patches, shape: tuple[int, int], *, grid_step: float = 32.0,
                 denoise: bool = True, n_image: int | None = None,
                 at: np.ndarray | None = None) -> ProductConvolution | None:
    """The image's own operator from its patches, as ``estimate_operator`` fits it (the
    few-beads models for an image of up to
    :data:`~napari_psfspace.core.model.fewbeads.FEW_BEADS` beads, the thin-plate field
    above); None where it has too few beads (:data:`MIN_BEADS_OWN`).

    ``n_image``: the image's usable beads when ``patches`` are its training beads only
    (``estimate_operator`` chooses the model by the image's count, then fits it to the
    training beads to judge it on the others); default ``len(patches)``. ``at``: only
    the PSFs at these positions (row, column; held-out beads) will be asked for, and
    the thin-plate field is kept in the cone only around them (the projection is most
    of the operator's assembly); the few-beads models ignore it.
    """
    mine = patches  # (image_patches left out the faint detections, as estimate does)
    if len(mine) < MIN_BEADS_OWN:
        return None
    try:
        if (len(mine) if n_image is None else int(n_image)) <= FEW_BEADS:
            support = radial_distance(mine.size) < mine.r_ext
            return fit_few_beads(mine, shape, support=support, grid_step=grid_step).operator
        return fit_patches(mine, shape, grid_step=grid_step, denoise=denoise, at=at)[1]
    except (ValueError, np.linalg.LinAlgError):  # no own estimate: the family stays
        return None


def blend(family_operator: ProductConvolution, own_operator: ProductConvolution,
          weight: float, *, metadata: dict | None = None) -> ProductConvolution:
    """The operator whose PSFs are ``weight h_family + (1 - weight) h_own``.

    Both operators' maps lie on one coarse grid (the same ``grid_step`` and image
    shape); the blend's basis is both bases, its maps both maps, scaled.

    Returns
    -------
    ProductConvolution
        With ``I_family + I_own`` basis PSFs (only the own operator for ``weight = 0``,
        only the family's for 1).
    """
    w = float(weight)
    if not 0.0 <= w <= 1.0:
        raise ValueError(f"`weight` must lie in [0, 1], got {weight!r}")
    if w == 0.0:
        return own_operator
    if w == 1.0:
        return family_operator
    gf, go = family_operator.grid, own_operator.grid
    if family_operator.image_shape != own_operator.image_shape or gf is None:
        raise ValueError("the two operators must share the image shape, and the family's "
                         f"maps a coarse grid, got {family_operator.shape}, "
                         f"{own_operator.shape}")
    if family_operator.psf_size != own_operator.psf_size:
        raise ValueError(f"the two operators' PSF sizes differ: {family_operator.psf_size} "
                         f"and {own_operator.psf_size}")
    same = go is not None and all(a.shape == b.shape and np.allclose(a, b)
                                  for a, b in zip(gf, go, strict=True))
    if same:
        own_maps = own_operator.coefficients
    else:  # (a few-beads model on its own grid) its maps at the family's nodes
        own_maps = np.stack([[own_operator.coefficients_at(y, x) for x in gf[1]]
                             for y in gf[0]]).transpose(2, 0, 1)
    basis = np.concatenate([family_operator.basis, own_operator.basis])
    maps = np.concatenate([w * family_operator.coefficients, (1.0 - w) * own_maps])
    return ProductConvolution(basis, maps, shape=family_operator.image_shape, grid=gf,
                              metadata=metadata)


@dataclass
class Choice:
    """The held-out judgement of one image's operators.

    Attributes
    ----------
    weight : float
        The family's weight kept (1: the family's operator, 0: the image's own).
    family, own : HeldoutResiduals or None
        The residuals of the two operators on the image's held-out beads (None: not
        judged).
    kept : HeldoutResiduals or None
        Those of the blend kept.
    reason : str
    by_weight : dict of float to float
        The mean held-out residual at each weight tried.
    prior : float or None
        The weight leant to among those the held-out beads cannot tell apart
        (:func:`prior_weight`; None: not judged).
    """

    weight: float
    family: HeldoutResiduals | None
    own: HeldoutResiduals | None
    kept: HeldoutResiduals | None
    reason: str
    by_weight: dict
    prior: float | None = None

    @property
    def model(self) -> str:
        """"family", "own" or "blend"."""
        return {1.0: "family", 0.0: "own"}.get(self.weight, "blend")

    def to_dict(self) -> dict:
        """JSON-ready record."""
        out: dict = {"model": self.model, "family_weight": self.weight,
                     "reason": self.reason}
        for name, res in (("family", self.family), ("own", self.own), ("kept", self.kept)):
            if res is not None and len(res.residual):
                out[f"heldout_{name}"] = float(np.mean(res.residual))
        if self.family is not None:
            out["n_heldout"] = int(len(self.family.residual))
        if self.by_weight:
            out["heldout_by_weight"] = {f"{w:g}": v for w, v in self.by_weight.items()}
        if self.prior is not None:
            out["prior_weight"] = float(self.prior)
        return out


def choose(family, k: int, own_operator: ProductConvolution | None,
           held: Patches | None) -> Choice:
    """The family's weight that best explains the image's held-out beads.

    Parameters
    ----------
    family : OperatorFamily
        The family learnt without the held-out beads (its ``metadata["field_share"]``,
        when there, and the held-out beads' noise set each image's :func:`prior_weight`).
    k : int
        The image's index in ``family``.
    own_operator : ProductConvolution or None
        The image's own estimate from the same training beads (None: none possible).
    held : Patches or None
        The image's held-out beads.

    Returns
    -------
    Choice
    """
    if held is None or len(held) == 0:
        return Choice(1.0, None, None, None, "no held-out beads: the family's operator", {})
    shares = family.metadata.get("field_share")
    share = shares[k] if shares is not None and k < len(shares) else 1.0
    floor = float(np.median(noise_floors(held)))
    prior = prior_weight(share, floor)
    return choose_between(family.psfs_at(k, held.centers), own_operator, held, prior=prior,
                          faint=floor >= NOISE_FLOOR_RANGE[1])


def choose_between(family_psfs: np.ndarray, own_operator: ProductConvolution | None,
                   held: Patches, *, prior: float = PRIOR_WEIGHT,
                   faint: bool = False) -> Choice:
    """The family's weight that best explains held-out beads, given the family's PSFs at
    them (``family_psfs``, (B, P, P)) and the image's own estimate from the other beads
    (None: none possible); :func:`pick_weight` with ``prior`` and ``faint``. See
    :func:`choose`."""
    fam_psf = family_psfs
    fam = residuals_of(fam_psf, held)
    if own_operator is None:
        return Choice(1.0, fam, None, fam, f"fewer than {MIN_BEADS_OWN} training beads: "
                                           "the family's operator", {})
    own_psf = np.array([own_operator.psf_at(y, x) for y, x in held.centers])
    own = residuals_of(own_psf, held)
    if len(held) < MIN_HELDOUT:
        return Choice(1.0, fam, own, fam, f"{len(held)} held-out beads, fewer than "
                                          f"{MIN_HELDOUT} to judge by: the family's operator",
                      {})
    res = {w: residuals_of(w * fam_psf + (1 - w) * own_psf, held) for w in WEIGHTS}
    by_weight = {w: float(np.mean(r.residual)) for w, r in res.items()}
    best, beaten = pick_weight({w: r.residual for w, r in res.items()}, prior=prior,
                               faint=faint)
    if not beaten:
        reason = (f"the image's own estimate: no family weight explains its held-out beads "
                  f"better beyond their scatter (best {best:g}: {by_weight[best]:.4f} "
                  f"against {by_weight[0.0]:.4f})")
        return Choice(0.0, fam, own, own, reason, by_weight, prior)
    reason = (f"family weight {best:g}: held-out residual {by_weight[best]:.4f} (the "
              f"family's alone {by_weight[1.0]:.4f}, the image's own {by_weight[0.0]:.4f}; "
              f"prior weight {prior:.2f})")
    return Choice(best, fam, own, res[best], reason, by_weight, prior)


def pick_weight(residuals: dict, prior: float = PRIOR_WEIGHT,
                faint: bool = False) -> tuple[float, bool]:
    """The family's weight from each weight's per-bead held-out residuals.

    1. The best weight (least mean residual; ties: the family's side), and the weights
       the beads cannot tell from it (the mean of the paired differences within one
       standard error): with 20 held-out beads the curve over the weights is flat
       within its scatter and its minimum wanders away from the weight the truth
       prefers (``bench/bench_family_oracle.py``).
    2. Of those, the weights that beat the image's own estimate (0) beyond one standard
       error of the paired differences: the single estimate is left only on the
       held-out beads' evidence. None: the own estimate stays.
    3. Of those, the one nearest ``prior``.

    With ``faint`` (each held-out bead mostly noise: their median noise floor at or
    above the top of :data:`NOISE_FLOOR_RANGE`) the burden of proof turns: such beads
    cannot show a weight better than the own estimate, and the own estimate, learnt
    from beads as noisy, is then mostly noise itself (the family pools every image's).
    Step 2 is left out: of the weights the beads cannot tell from the best, the one
    nearest ``prior``; the own estimate stays only where the beads show it better than
    every other weight beyond their scatter.

    Parameters
    ----------
    residuals : dict of float to ndarray of shape (B,)
        Per-bead residuals at each weight of :data:`WEIGHTS` (the same beads, in the
        same order).
    prior : float
        The weight leant to (:func:`prior_weight`).
    faint : bool
        The beads are mostly noise (see above).

    Returns
    -------
    weight : float
    beaten : bool
        Whether the weight beat the own estimate (False: ``weight`` is the one the beads
        preferred, but 0 is kept).
    """
    def se(d):
        return float(np.std(d, ddof=1)) / np.sqrt(len(d))

    def nearest(ws):
        return min(ws, key=lambda w: (abs(w - prior), -w))

    means = {w: float(np.mean(r)) for w, r in residuals.items()}
    best = min(residuals, key=lambda w: (means[w], -w))
    close = [w for w in residuals
             if w == best or means[w] - means[best] <= se(residuals[w] - residuals[best])]
    if 0.0 not in residuals or faint:
        return nearest(close), True
    beating = [w for w in close if w != 0.0
               and float(np.mean(residuals[w] - residuals[0.0]))
               < -se(residuals[w] - residuals[0.0])]
    if beating:
        return nearest(beating), True
    if 0.0 in close:
        return 0.0, True
    return nearest(close), False
