"""Which of a few clicked beads disagrees with the others.

Among five clicked beads one may be a pair too close to resolve, saturated, or lying on a
structure; an operator identified from five bends towards it, and the four others then
disagree with the result as much as it does. Each bead is therefore judged left out: the
image's coordinates fitted to the other beads (:func:`~napari_psfspace.core.family.
coordinates.fit_coordinates`, with the family's miss kriged from their residuals) predict
its coefficients, and its score is its squared residual in the PSF's norm over the one
expected,

    rho_p = ||c_p / g_p - pred_p||^2 / (I sd_p^2 / g_p^2 + var_p),

``sd_p / g_p`` its per-pixel noise at unit amplitude (the noise of its ``I`` coefficients
on the PSF basis adds ``I sd^2`` to the squared norm) and ``var_p`` the prediction's own
variance (the coordinates' and the miss's, larger at the rim). A single bead scores about
1. A bad bead bends the fit that predicts each of the others, so that one of them may
score above it: the bead judged is the one whose absence leaves the others agreeing best
(the least mean score of their residuals about the fit without it).

A bead can disagree with the others for two reasons: it is not a single point (a pair, a
saturated core, a structure under it), or the family's model misses this image there (a
place or a condition it represents poorly). Left out, the second takes away the very
information the others lack. Its shape tells them apart: a single bead's PSF is one the
family's PSF basis holds, whatever the condition, so its patch's energy outside the
basis is about its noise's; a pair, a clipped core or a ridge leaves more
(:func:`shape_scores`). The judged bead is left out when its score is above
:data:`OUTLIER` and its shape score above :data:`SHAPE_OUTLIER`, and the others are
judged again without it, at most a fifth of the beads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..family.coordinates import Model, design, fit_coordinates, krige_miss, whitened
from ..family.curve import Curve

#: The score above which a clicked bead is left out. On simulated images from three
#: optics codes (``bench/bench_bead_check.py``), single beads judged in sets of five
#: score above it in a few percent of the sets, and an unresolved pair, a saturated bead
#: or a bead under a bright line are caught in most: a bad bead kept costs more than
#: one of five good beads left out.
OUTLIER = 10.0
#: The shape score (energy of a patch outside the family's PSF basis, in units of its
#: noise's) above which a disagreeing bead is taken for not a single point. Single beads
#: of simulated images from three optics codes stay below it but for a few percent, and
#: unresolved pairs, clipped cores and beads under a line are above it in most
#: (``bench/bench_bead_check.py``).
SHAPE_OUTLIER = 2.0
#: Fewest beads judged: with fewer, a left-out bead is predicted from two.
MIN_JUDGED = 4
#: Largest share of the beads left out.
MOST_LEFT_OUT = 0.2
#: Most beads each refitted without one bead (and the miss kriged from the others to
#: predict it); beyond, :func:`leave_one_out` downdates the full fit.
MAX_KRIGED_CHECK = 12


@dataclass
class BeadCheck:
    """The judgement of the clicked beads (:func:`check_beads`).

    Attributes
    ----------
    keep : ndarray of shape (P,), bool
        The beads kept.
    scores : ndarray of shape (P,)
        Each bead's score when it was judged last (NaN below :data:`MIN_JUDGED` beads).
    left_out : list of int
        The beads left out, in the order they were.
    shapes : ndarray of shape (P,), optional
        Each bead's shape score (:func:`shape_scores`; None: not given).
    """

    keep: np.ndarray
    scores: np.ndarray
    left_out: list
    shapes: np.ndarray | None = None


def shape_scores(psf: np.ndarray, coefficients: np.ndarray, basis: np.ndarray,
                 noise: np.ndarray, window: np.ndarray) -> np.ndarray:
    """Each patch's energy outside the family's PSF basis in units of its noise's, (P,).

    Parameters
    ----------
    psf : ndarray of shape (P, S, S)
        The beads' windowed sum-1 patches.
    coefficients : ndarray of shape (P, I)
        Their least-squares coefficients on ``basis``.
    basis : ndarray of shape (I, S, S)
        The family's PSF basis.
    noise : ndarray of shape (P,)
        Per-pixel noise of each sum-1 patch before the window.
    window : ndarray of shape (S, S)
        The window the patches were multiplied by (its squares sum the noise's energy).

    Returns
    -------
    ndarray of shape (P,)
        About 1 for a single bead whatever its condition (the basis holds its PSF);
        more for a pair, a clipped core or a structure under it.
    """
    rec = np.einsum("pi,ixy->pxy", np.asarray(coefficients, np.float64), basis)
    res = ((np.asarray(psf, np.float64) - rec) ** 2).sum(axis=(1, 2))
    expected = np.asarray(noise, np.float64) ** 2 * float((np.asarray(window) ** 2).sum())
    return res / np.maximum(expected, 1e-300)


def _expected(model: Model, n_i: int, noise: float, a_p: np.ndarray, cov: np.ndarray,
              miss_var: float) -> float:
    """The expected squared residual of a bead: its noise's, and its prediction's."""
    return n_i * noise ** 2 + miss_var + float(np.trace(model.gram @ a_p @ cov @ a_p.T))


def leave_one_out(model: Model | Curve, c: np.ndarray, sd: np.ndarray,
                  centers: np.ndarray, *,
                  n_directions: int | None = None,
                  amplitude_range: tuple[float, float] = (0.5, 2.0)
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Each bead's score (P,) predicted from the others (see the module's notes), and how
    well the others then agree among themselves (P,): the mean score of their own
    residuals about the fit without that bead.

    Up to :data:`MAX_KRIGED_CHECK` beads each fit without a bead is made anew (a bad
    bead's pull on the others' amplitudes goes with it); beyond, one bead moves the
    others' amplitudes little, and the fit without it is the full fit's normal equations
    less its rows, at the full fit's amplitudes (the miss not kriged: its short reach
    adds little to a prediction from many beads).
    """
    c = np.asarray(c, np.float64)
    sd = np.asarray(sd, np.float64)
    n_p, n_i = c.shape
    if isinstance(model, Curve):  # judged on the curve's lines at these beads' fit
        model, _ = model.fit(c, sd, centers, amplitude_range=amplitude_range)
    at = design(model, centers)
    if n_p > MAX_KRIGED_CHECK:
        return _downdated(model, c, sd, centers, at, n_directions, amplitude_range)
    prior_miss = model.miss_var(centers)  # each bead's
    scores, rest_scores = np.empty(n_p), np.empty(n_p)
    for p in range(n_p):
        rest = np.arange(n_p) != p
        fit = fit_coordinates(model, c[rest], sd[rest], centers[rest],
                              n_directions=n_directions, amplitude_range=amplitude_range,
                              at_beads=(at[0][rest], at[1][rest]))
        a_p = at[1][p, :, :len(fit.z)]  # (I, L)
        add, miss_var = krige_miss(model, fit, centers[p:p + 1])
        pred = at[0][p] + a_p @ fit.z + add[0]
        scores[p] = _score(model, c[p], float(sd[p]), pred, amplitude_range,
                           float(np.trace(model.gram @ a_p @ fit.cov @ a_p.T))
                           + float(miss_var[0]))
        rest_scores[p] = float(np.mean(
            [float(q @ model.gram @ q) / max(n_i * noise ** 2 + miss, 1e-300)
             for q, noise, miss in zip(fit.residuals, fit.noise, prior_miss[rest],
                                       strict=True)]))
    return scores, rest_scores


def _score(model: Model, c: np.ndarray, sd: float, pred: np.ndarray, amplitude_range,
           var: float) -> float:
    """A bead's squared residual about ``pred`` (its amplitude fitted) over the expected
    one: its noise's (``I sd^2 / g^2``) and the prediction's variance ``var``."""
    mm = float(pred @ model.gram @ pred)
    g = float(np.clip(pred @ model.gram @ c / mm if mm > 0 else 1.0, *amplitude_range))
    r = c / g - pred
    return float(r @ model.gram @ r) / max(len(c) * (sd / g) ** 2 + var, 1e-300)


def _downdated(model, c, sd, centers, at, n_directions, amplitude_range):
    """:func:`leave_one_out` for many beads: each fit without a bead from the full fit's
    normal equations less that bead's rows."""
    n_p, n_i = c.shape
    full = fit_coordinates(model, c, sd, centers, n_directions=n_directions,
                           amplitude_range=amplitude_range, at_beads=at)
    n_l = len(full.z)
    g, base, a = full.amplitudes, at[0], at[1][:, :, :n_l]
    cw, bw, aw = whitened(model.gram, c, base, a)
    aw = aw * (g / sd)[:, None, None]  # rows of each bead
    yw = (cw - g[:, None] * bw) / sd[:, None]
    lhs = np.einsum("pil,pim->lm", aw, aw) + np.diag(
        1.0 / np.maximum(model.variances[:n_l], 1e-300))
    rhs = np.einsum("pil,pi->l", aw, yw)
    prior_miss = model.miss_var(centers)  # each bead's
    scores, rest_scores = np.empty(n_p), np.empty(n_p)
    for p in range(n_p):
        lhs_p = lhs - aw[p].T @ aw[p]
        z = np.linalg.solve(lhs_p, rhs - aw[p].T @ yw[p])
        cov = np.linalg.inv(lhs_p)
        pred = base[p] + a[p] @ z
        scores[p] = _score(model, c[p], float(sd[p]), pred, amplitude_range,
                           float(np.trace(model.gram @ a[p] @ cov @ a[p].T))
                           + float(prior_miss[p]))
        res = c / g[:, None] - (base + a @ z)
        own = np.einsum("pi,ij,pj->p", res, model.gram, res) / (
            n_i * (sd / g) ** 2 + prior_miss)
        rest_scores[p] = float((own.sum() - own[p]) / (n_p - 1))
    return scores, rest_scores


def check_beads(model: Model | Curve, c: np.ndarray, sd: np.ndarray, centers: np.ndarray, *,
                shapes: np.ndarray | None = None, n_directions: int | None = None,
                amplitude_range: tuple[float, float] = (0.5, 2.0),
                outlier: float = OUTLIER, shape_outlier: float = SHAPE_OUTLIER
                ) -> BeadCheck:
    """Leave out the clicked beads that disagree with the others, the worst first.

    Parameters
    ----------
    model : Model or Curve
        The family's few-dimensional model (a curve is judged on its lines at the fit
        of the beads judged).
    c : ndarray of shape (P, I)
        The beads' coefficients on the family's PSF basis.
    sd : ndarray of shape (P,)
        Per-pixel noise of each bead's sum-1 patch.
    centers : ndarray of shape (P, 2)
        Their positions, pixels.
    shapes : ndarray of shape (P,), optional
        Their shape scores (:func:`shape_scores`); None: a bead is left out on its score
        alone.
    n_directions : int, optional
        ``L``; default the model's.
    amplitude_range : (float, float)
        Range of each bead's amplitude.
    outlier, shape_outlier : float
        The score and the shape score above which a bead is left out.

    Returns
    -------
    BeadCheck
    """
    c = np.asarray(c, np.float64)
    n_p = len(c)
    keep = np.ones(n_p, bool)
    scores = np.full(n_p, np.nan)
    left: list[int] = []
    most = int(np.floor(MOST_LEFT_OUT * n_p))
    while keep.sum() >= MIN_JUDGED:
        idx = np.flatnonzero(keep)
        s, rest = leave_one_out(model, c[idx], np.asarray(sd)[idx],
                                np.asarray(centers)[idx], n_directions=n_directions,
                                amplitude_range=amplitude_range)
        scores[idx] = s
        # the bead whose absence leaves the others agreeing best: a bad bead bends the
        # fit that predicts each other bead, so that theirs may score above its own
        worst = int(np.argmin(rest))
        odd = shapes is None or shapes[idx[worst]] > shape_outlier
        if s[worst] <= outlier or not odd or len(left) >= most:
            break
        keep[idx[worst]] = False
        left.append(int(idx[worst]))
    return BeadCheck(keep, scores, left,
                     None if shapes is None else np.asarray(shapes, np.float64))
