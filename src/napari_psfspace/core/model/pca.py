"""Low-dimensional PSF basis by principal component analysis (paper, App. A, sec. 2.5).

The patches (sum 1, then l2-normalised so that every bead weighs the same) are
decomposed by an SVD. Without centring, the first component carries the mean PSF,
so every PSF is ``sum_i beta_i h_i`` with no separate mean term, as the
product-convolution model needs. Unlikely patches (doublets, debris) are removed, then
the PCA is recomputed: with positions, each bead is judged by its held-out error against
its neighbours and rejected only for a held-out gain
(:func:`~napari_psfspace.core.model.outliers.judge_outliers`); without,
the paper's z-score test at 3 sigma on the coefficients; a family's images are each
tested on a robust scale (:data:`GROUP_Z`).

The basis size is where the cross-validated error of the whole model (basis and
thin-plate field learnt without the beads it predicts) is least
(:func:`~napari_psfspace.core.model.outliers.size_by_heldout`), or Gavish &
Donoho's optimal hard threshold for an unknown noise level: keep the singular values
above ``omega(beta) * sigma_med``, where ``omega(1) = 2.858`` is the value quoted in the
paper (square matrices) and ``omega(beta)`` its published polynomial approximation for an
aspect ratio ``beta``. Both are capped at what the number of beads supports; the rule,
which no held-out bead checks, at :data:`RULE_CAP`. The paper capped the size at 12; on
wide strongly aberrated fields the held-out error still falls beyond it
(``bench/bench_caps.py``), hence :data:`HELDOUT_CAP`.

**Outliers by position.** With field-dependent aberrations the paper's global z-test
rejects the legitimately extreme beads at the field's edges and leaves the corners to
extrapolation; with positions each bead is judged by one statistic, its held-out error
against the others.

**A family's images** (``groups``): the beads of a family's images under other conditions
are not a bead's neighbours. Tested against the pooled patches, the beads of a condition at
the edge of those learnt are all outliers, and the family loses that condition where it
differs most (a corner of a tilted field). Each patch is instead tested against the
thin-plate fit of its own image's beads: its in-sample residual over ``sqrt(1 - S_mm)``
(the spline's standardized residual: its leverage, large where the field is extrapolated
at the rim, does not inflate it as the leave-one-out residual's ``1 / (1 - S_mm)`` does),
scaled by ``1.4826`` times the image's median absolute deviation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..common.progress import check_halt
from .outliers import (
    JUDGE_COMPONENTS,
    crossvalidated_basis_errors,
    judge_outliers,
    size_by_heldout,
)
from .tps import ThinPlateSpline


@dataclass
class PsfBasis:
    """Result of :func:`learn_basis`.

    Attributes
    ----------
    basis : ndarray of shape (I, P, P)
        Orthonormal PSF basis ``h_i`` (l2 norm 1 each).
    coefficients : ndarray of shape (K_in, I)
        ``beta_{i,m} = <p_m, h_i>`` of the sum-1 patches of the inliers.
    inliers : ndarray of shape (K,), bool
        Patches kept after the z-score test.
    zscores : ndarray of shape (K,)
        Without positions, the largest absolute z-score of each patch's coefficients
        (first PCA); with positions, its held-out error in robust standard deviations
        (NaN where ``z_threshold`` is infinite: no bead judged); with ``groups``, its
        largest standardized residual about its image's field, in robust standard
        deviations.
    singular_values : ndarray
        Singular values of the inlier matrix (second PCA), decreasing.
    rank_threshold : float
        Gavish-Donoho threshold on the singular values.
    n_psf_rule : int
        Basis size that the threshold rule gives (whether or not it was used).
    heldout_errors : ndarray of shape (I_max,) or None
        Relative cross-validated error for each basis size, when ``n_psf`` was
        chosen by held-out beads.
    components : ndarray of shape (M, S) or None
        The first ``M`` principal directions of the inliers (second PCA) on the
        ``support`` pixels, when ``components=M`` was asked for.
    """

    basis: np.ndarray
    coefficients: np.ndarray
    inliers: np.ndarray
    zscores: np.ndarray
    singular_values: np.ndarray
    rank_threshold: float
    n_psf_rule: int
    heldout_errors: np.ndarray | None = None
    components: np.ndarray | None = None

    @property
    def n_psf(self) -> int:
        return self.basis.shape[0]


def omega(beta: float) -> float:
    """Gavish-Donoho optimal hard-threshold factor for unknown noise (aspect ``beta`` <= 1)."""
    return 0.56 * beta**3 - 0.95 * beta**2 + 1.82 * beta + 1.43


def rank_by_threshold(singular_values: np.ndarray, shape: tuple[int, int]) -> tuple[int, float]:
    """Number of singular values above ``omega(beta) * median``, and that threshold."""
    m, n = shape
    beta = min(m, n) / max(m, n)
    s = np.asarray(singular_values)
    tau = omega(beta) * float(np.median(s))
    return max(1, int(np.count_nonzero(s > tau))), tau


#: Least ratio of the median singular value to the largest that :func:`singular_values`
#: takes from the Gram matrix: there its relative error (about ``eps`` over the ratio
#: squared) stays near 1e-6, far below any change of the rule's threshold that a bead's
#: noise makes; below it, the full SVD.
GRAM_MEDIAN_RATIO = 1e-5


def singular_values(x: np.ndarray) -> np.ndarray:
    """The singular values of ``x`` (N, S), descending: the square roots of the
    eigenvalues of its smaller Gram matrix (a family's pooled patches make a tall matrix,
    whose full SVD costs several times more), or the full SVD where the median value is
    under :data:`GRAM_MEDIAN_RATIO` of the largest (the Gram matrix squares the
    condition)."""
    x = np.asarray(x, np.float64)
    gram = x.T @ x if x.shape[0] >= x.shape[1] else x @ x.T
    s = np.sqrt(np.clip(np.linalg.eigvalsh(gram)[::-1], 0.0, None))
    if not len(s) or s[0] == 0 or np.median(s) >= GRAM_MEDIAN_RATIO * s[0]:
        return s
    return np.linalg.svd(x, compute_uv=False)


def min_beads_for(n_psf: int) -> int:
    """Fewest usable beads for a basis of ``n_psf`` elements: ``max(5, 2 n_psf + 2)``."""
    return max(5, 2 * n_psf + 2)


def _svd(x: np.ndarray, k: int | None, method: str, seed: int = 0):
    """Thin SVD, full, randomized (Halko et al.) when ``k`` is given, or "gram": from the
    eigendecomposition of the smaller Gram matrix (faster than the full SVD for the
    pooled patches of a family, whose matrix is tall; singular values below ``sqrt(eps)`` of the
    largest lose their relative precision, far below any bead's noise)."""
    if method == "gram":
        if x.shape[0] >= x.shape[1]:
            w, v = np.linalg.eigh(x.T @ x)
            order = np.argsort(w)[::-1]
            s = np.sqrt(np.clip(w[order], 0, None))
            return s, v[:, order].T
        w, u = np.linalg.eigh(x @ x.T)
        order = np.argsort(w)[::-1]
        s = np.sqrt(np.clip(w[order], 0, None))
        keep = s > s[0] * 1e-7 if len(s) and s[0] > 0 else np.zeros(len(s), bool)
        vt = np.zeros((len(s), x.shape[1]))  # rows of null singular values: left at 0
        vt[keep] = (u[:, order[keep]].T @ x) / s[keep][:, None]
        return s, vt
    if method == "full" or k is None:
        _, s, vt = np.linalg.svd(x, full_matrices=False)
        return s, vt
    rng = np.random.default_rng(seed)
    q = min(k + 10, min(x.shape))
    y = x @ rng.standard_normal((x.shape[1], q))
    for _ in range(4):  # power iterations, re-orthonormalised
        y, _ = np.linalg.qr(y)
        y, _ = np.linalg.qr(x @ (x.T @ y))
    b = y.T @ x
    _, s, vt = np.linalg.svd(b, full_matrices=False)
    return s, vt


def orient(vt: np.ndarray) -> np.ndarray:
    """Deterministic signs: the first component sums positive, the others have a positive
    largest-magnitude entry."""
    vt = vt.copy()
    if vt[0].sum() < 0:
        vt[0] = -vt[0]
    for i in range(1, len(vt)):
        if vt[i, np.argmax(np.abs(vt[i]))] < 0:
            vt[i] = -vt[i]
    return vt


#: Default cap of the Gavish-Donoho rule's basis size (the paper's 12): the rule has no
#: held-out check, and on noisy pooled patches it keeps noise components.
RULE_CAP = 12

#: Default cap of the held-out basis size: beyond it the cross-validated error of the
#: scene set's fields falls by a fraction of a percent, while every component costs the
#: operator two FFTs and the cross-validation's smoothing choice grows with it
#: (``bench/bench_caps.py``, ``bench/bench_speed.py``).
HELDOUT_CAP = 30

#: Threshold of the grouped test (``groups``), in robust standard deviations of each
#: image's standardized residuals: a gross-misfit gate. Good beads' residuals about a
#: field are heavy-tailed (faint beads, the steep field at the rim), and the family's
#: fields already weigh moderate misfits down; at this threshold the gate keeps the rim's
#: beads and still rejects doublets and noise patches put into a family's images
#: (``bench/bench_family_outliers.py``, three generators).
GROUP_Z = 10.0

#: Fewest beads of an image for the grouped test: its robust scale needs a few.
GROUP_MIN_BEADS = 6


def learn_basis(
    psfs: np.ndarray,
    n_psf: int | str | None = None,
    *,
    support: np.ndarray | None = None,
    positions: np.ndarray | None = None,
    z_threshold: float | None = None,
    svd: str = "auto",
    max_psf: int | None = None,
    weights: np.ndarray | None = None,
    components: int = 0,
    groups: np.ndarray | None = None,
) -> PsfBasis:
    """Learn an orthonormal PSF basis from sum-normalised patches.

    Parameters
    ----------
    psfs : ndarray of shape (K, P, P), or (K, Z, P, P) for 3D patches
        Background-free PSF patches, each summing to 1 (a 3D patch: its own
        normalisation; the basis has the patches' shape).
    n_psf : int, "heldout", "rule" or None
        Basis size ``I``. "heldout" (the default when ``positions`` are given): where the
        whole model's cross-validated error is least
        (:func:`~napari_psfspace.core.model.outliers.size_by_heldout`); "rule" (the
        default without): the Gavish-Donoho threshold (module docstring).
    support : ndarray of the patches' shape, bool, optional
        Pixels where the windowed patches can be non-zero (the window support). Only
        these enter the rank rule's aspect ratio and median. Default: all pixels.
    positions : ndarray of shape (K, 2), optional
        Bead positions (row, column): each patch is then judged by its held-out error
        against the others (:func:`~napari_psfspace.core.model.outliers.judge_outliers`).
    z_threshold : float, optional
        Patches with a coefficient more than ``z_threshold`` standard deviations from
        the mean are rejected. Default 3 (the paper's); with ``positions``, the robust
        standard deviations above which :func:`judge_outliers` asks for a held-out gain;
        with ``groups``, :data:`GROUP_Z` robust standard deviations (see ``groups``).
    svd : {"auto", "full", "randomized", "gram"}
        SVD method. "auto" uses the full SVD unless both dimensions exceed 2000
        and ``n_psf`` is given; "gram" the eigendecomposition of the Gram matrix (the
        family's pooled patches: faster, as precise in the leading components).
    max_psf : int, optional
        Upper bound of the automatic basis size, besides the ``(K - 2) // 2`` that the
        inliers support. Default: :data:`HELDOUT_CAP`, or :data:`RULE_CAP` for the rule.
    weights : ndarray of shape (K,), optional
        Weight of each patch in the SVD (its row is scaled by ``sqrt(weights)``).
        Default ``1 / ||p_m||^2`` (each bead weighs the same); for denoised patches, the
        raw patches' (a faint bead's noise still lowers its weight).
    components : int
        Also return the first ``components`` principal directions of the inliers
        (:attr:`PsfBasis.components`; 0: none).
    groups : ndarray of shape (K,), optional
        The image each patch comes from, with ``positions`` on each image's own field:
        each patch is tested against the thin-plate fit of its own image's beads (module
        docstring); images of fewer than :data:`GROUP_MIN_BEADS` beads are not tested.
        Needs an integer ``n_psf`` or "rule".

    Returns
    -------
    PsfBasis

    Raises
    ------
    ValueError
        Too few patches for the requested basis size.
    """
    check_halt()
    psfs = np.asarray(psfs, dtype=np.float64)
    k, patch_shape = psfs.shape[0], psfs.shape[1:]
    n_psf, select = _size_rule(psfs, n_psf, positions, svd)
    pos, groups, mask, xn = _normalised(psfs, support, positions, weights, groups, patch_shape, k,
                                        select)
    method = svd
    if svd == "auto":
        method = "randomized" if (min(xn.shape) > 2000 and n_psf is not None) else "full"
    # First PCA, z-score test on the coefficients (at most 5: doublets and debris show
    # in the leading components; more tests only add false alarms).
    s, vt = _svd(xn, n_psf, method)
    n_first = n_psf if n_psf is not None else min(5, _n_from_rule(s, xn.shape, k, max_psf)[2])
    coef = xn @ vt[:n_first].T
    inliers, zmax = _inliers(n_psf, z_threshold, groups, k, pos, xn, vt, n_first, coef)
    # Second PCA on the inliers.
    n_in = int(np.count_nonzero(inliers))
    s, vt = _svd(xn[inliers], n_psf, method)
    rule, tau, capped = _n_from_rule(s, xn[inliers].shape, n_in, max_psf)
    heldout_errors, n_final = _final_size(psfs, n_psf, max_psf, select, pos, mask, xn, vt, inliers,
                                          n_in, capped)
    more = vt[:int(components)].copy() if components else None
    vt = orient(vt[:n_final])
    basis = np.zeros((n_final, *patch_shape))
    basis[:, mask] = vt
    beta = psfs[inliers][:, mask] @ vt.T
    return PsfBasis(basis, beta, inliers, zmax, s, tau, rule, heldout_errors, more)


def _n_from_rule(s, shape, count, max_psf):
    """The rule's size, its threshold, and the size capped at what ``count`` beads
    support and at ``max_psf`` (default :data:`RULE_CAP`)."""
    rule, tau = rank_by_threshold(s, shape)
    cap = max(1, (count - 2) // 2)
    return rule, tau, min(rule, cap, RULE_CAP if max_psf is None else max_psf)


def _size_rule(psfs, n_psf, positions, svd):
    """How the basis size is chosen (``select``: "heldout", "rule" or None for a given size)
    and the size given, checked against the beads there are."""
    if psfs.ndim not in (3, 4) or psfs.shape[-1] != psfs.shape[-2]:
        raise ValueError(f"`psfs` must have shape (K, P, P) or (K, Z, P, P), got "
                         f"{psfs.shape}.")
    k = psfs.shape[0]
    if svd not in ("auto", "full", "randomized", "gram"):
        raise ValueError(f"`svd` must be 'auto', 'full', 'randomized' or 'gram', got {svd!r}.")
    if n_psf is None:
        n_psf = "heldout" if positions is not None else "rule"
    if isinstance(n_psf, str):
        if n_psf not in ("heldout", "rule"):
            raise ValueError(f"`n_psf` must be a positive integer, 'heldout', 'rule' or None, "
                             f"got {n_psf!r}.")
        if n_psf == "heldout" and positions is None:
            raise ValueError("`n_psf` = 'heldout' needs the bead `positions`.")
        select, n_psf = n_psf, None
    else:
        select = None
        if int(n_psf) != n_psf or n_psf < 1:
            raise ValueError(f"`n_psf` must be a positive integer or None, got {n_psf!r}.")
        n_psf = int(n_psf)
    if k < min_beads_for(n_psf or 1):
        if n_psf is None:
            raise ValueError(
                f"Too few beads to learn a PSF basis: need at least {min_beads_for(1)} usable "
                f"beads, got {k}."
            )
        raise ValueError(
            f"Too few beads for a basis of `n_psf` = {n_psf}: need at least "
            f"{min_beads_for(n_psf)} usable beads, got {k}. Lower `n_psf` or use more beads."
        )
    return n_psf, select


def _normalised(psfs, support, positions, weights, groups, patch_shape, k, select):
    """The patches' pixels on the support, each normalised (to unit norm, or by its weight),
    the beads' positions and groups checked."""
    pos = None if positions is None else np.asarray(positions, dtype=np.float64).reshape(k, 2)
    if groups is not None:
        groups = np.asarray(groups).reshape(-1)
        if pos is None or groups.shape != (k,):
            raise ValueError(f"`groups` needs `positions` and one group per patch ({k}), got "
                             f"{groups.shape[0]} groups"
                             + ("" if pos is not None else " and no positions"))
        if select == "heldout":
            raise ValueError("`groups` needs `n_psf` an integer or 'rule': the held-out "
                             "choice of the size fits one field")
    mask = np.ones(patch_shape, bool) if support is None else np.asarray(support, bool)
    x = psfs[:, mask]
    norms = np.linalg.norm(x, axis=1)
    if np.any(norms <= 0):
        raise ValueError("`psfs` holds an all-zero patch; drop faint beads first.")
    if weights is None:
        xn = x / norms[:, None]
    else:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.shape != (k,) or np.any(~np.isfinite(weights)) or np.any(weights <= 0):
            raise ValueError(f"`weights` must be {k} positive finite numbers.")
        xn = x * np.sqrt(weights / np.mean(weights * norms**2))[:, None]
    return pos, groups, mask, xn


def _inliers(n_psf, z_threshold, groups, k, pos, xn, vt, n_first, coef):
    """The outlier test on the first coefficients: per group of beads against a spline of
    the group's coefficients, a plain z-score without positions, or against what the beads'
    neighbours predict (:func:`judge_outliers`); every bead kept where too few would be
    left."""
    if groups is not None:
        zmax = np.zeros(k)
        for g in np.unique(groups):
            sel = groups == g
            if np.count_nonzero(sel) >= GROUP_MIN_BEADS:
                zmax[sel] = _robust_zmax(ThinPlateSpline(pos[sel], coef[sel])
                                         .standardized_residuals)
        threshold = GROUP_Z if z_threshold is None else z_threshold
        inliers = zmax <= threshold
    elif pos is None:
        zmax = _zmax(coef)
        inliers = zmax <= (3.0 if z_threshold is None else z_threshold)
    elif z_threshold is not None and np.isinf(z_threshold):  # every bead kept, unjudged
        zmax, inliers = np.full(k, np.nan), np.ones(k, bool)
    else:
        zmax, inliers = judge_outliers(xn, vt, pos, min(n_first, JUDGE_COMPONENTS),
                                       3.0 if z_threshold is None else z_threshold,
                                       min_keep=min_beads_for(n_psf or 1))
    if np.count_nonzero(inliers) < min_beads_for(n_psf or 1):
        inliers[:] = True  # too few left: keep everything rather than fail
    return inliers, zmax


def _final_size(psfs, n_psf, max_psf, select, pos, mask, xn, vt, inliers, n_in, capped):
    """The basis size: given, by the rule (capped), or where the beads' held-out error stops
    falling (with the mean held-out error of each size)."""
    heldout_errors = None
    if n_psf is not None:
        n_final = n_psf
    elif select == "rule":
        n_final = capped
    else:
        n_max = min(max(1, (n_in - 2) // 2), len(vt),
                    HELDOUT_CAP if max_psf is None else int(max_psf))
        per_bead = crossvalidated_basis_errors(psfs[inliers][:, mask], xn[inliers],
                                               pos[inliers], n_max)
        heldout_errors = per_bead.mean(axis=0)
        n_final = size_by_heldout(per_bead)
    return heldout_errors, n_final


def _robust_zmax(values: np.ndarray) -> np.ndarray:
    """Each row's largest absolute deviation from the column's median, in units of
    ``1.4826`` times the column's median absolute deviation (columns without spread:
    none)."""
    values = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    dev = np.abs(values - np.median(values, axis=0))
    scale = 1.4826 * np.median(dev, axis=0)
    ok = scale > 1e-12 * max(float(dev.max()), 1e-300)
    if not ok.any():
        return np.zeros(len(values))
    return (dev[:, ok] / scale[ok]).max(axis=1)


def _zmax(values: np.ndarray) -> np.ndarray:
    """Each row's largest absolute z-score over the columns of ``values`` (n, m)."""
    std = values.std(axis=0)
    std[std == 0] = 1.0
    return (np.abs(values - values.mean(axis=0)) / std).max(axis=1)
