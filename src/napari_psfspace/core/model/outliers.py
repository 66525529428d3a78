"""Which beads' patches the PCA leaves out, and how many components it keeps, judged by
beads held out.

A bead's patch is judged by its own held-out error against the field its neighbours
predict, not by z-scores of its coefficients (:func:`judge_outliers`); a rejection that
the data cannot spare must lower the held-out error of the beads near it
(:func:`held_out_gain`). Both rest on :func:`heldout_basis_errors`, the closed-form
leave-one-bead-out error of the whole model (basis and thin-plate field). The basis size
is where the error of beads the model never saw is least (:func:`size_by_heldout`, on
:func:`crossvalidated_basis_errors`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..common.progress import check_halt
from ..common.threads import map_threads
from .tps import ThinPlateSpline

#: Neighbours that must surround a bead for :func:`judge_outliers` to compare it with
#: their prediction: the bead lies inside the convex hull of its nearest this many.
SURROUND_NEIGHBOURS = 6

#: Components :func:`judge_outliers` measures each bead's error against, at most: a
#: doublet or debris shows in the leading ones, and with many more the error left is the
#: field's fine structure, which a noise-free field makes tiny and the test then reads
#: as significant everywhere.
JUDGE_COMPONENTS = 5

#: Most basis sizes the held-out comparison of :func:`judge_outliers` looks at.
GAIN_COMPONENTS = 30

#: Robust standard deviations beyond which :func:`judge_outliers` rejects a bead without
#: asking for a held-out gain: a gross misfit (a doublet, debris, a bead far off focus)
#: changes the field only near itself, too few beads for a paired test to see; a
#: legitimately unusual bead (the rim of a steep field) stands a few deviations out (the
#: family's gate, :data:`~napari_psfspace.core.model.pca.GROUP_Z`, is the same).
GROSS_Z = 10.0

#: Standard errors by which the kept beads' held-out error must fall for a rejection
#: (:func:`held_out_gain`): a one-sided test at about 2 %.
GAIN_SE = 2.0

#: Folds of the cross-validation that sizes the basis (:func:`size_by_heldout`).
SIZE_FOLDS = 5


def surrounded(positions: np.ndarray, k: int = SURROUND_NEIGHBOURS) -> np.ndarray:
    """Which beads their ``k`` nearest neighbours surround, shape (K,), bool: the
    neighbours' directions leave no gap of a third of a turn or more, so the bead lies
    well inside their convex hull (a gap of half a turn puts it on the hull's edge, as a
    bead in a row along the field's border) and the field there is interpolated, not
    extrapolated."""
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    if len(pos) <= k:
        return np.zeros(len(pos), bool)
    _, idx = cKDTree(pos).query(pos, k=k + 1)
    vec = pos[idx[:, 1:]] - pos[:, None, :]
    ang = np.sort(np.arctan2(vec[..., 0], vec[..., 1]), axis=1)
    gaps = np.diff(np.concatenate([ang, ang[:, :1] + 2 * np.pi], axis=1), axis=1)
    return gaps.max(axis=1) < 2 * np.pi / 3


def _robust_z(values: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``values`` in robust standard deviations above the median of ``reference``
    (``1.4826`` times its median absolute deviation)."""
    med = float(np.median(reference))
    scale = 1.4826 * float(np.median(np.abs(reference - med)))
    return (values - med) / max(scale, 1e-12 * max(abs(med), 1e-300))


def _leading(x: np.ndarray, n: int) -> np.ndarray:
    """The ``n`` leading right singular vectors of ``x`` (K, S), shape (<= n, S), from
    the eigendecomposition of its smaller Gram matrix (a bead set's patches: far fewer
    rows than pixels, and only the leading directions are asked for)."""
    if x.shape[0] <= x.shape[1]:
        w, u = np.linalg.eigh(x @ x.T)
        order = np.argsort(w)[::-1][:n]
        s = np.sqrt(np.clip(w[order], 0.0, None))
        keep = s > 1e-7 * max(float(s[0]), 1e-300)
        return (u[:, order[keep]].T @ x) / s[keep, None]
    w, v = np.linalg.eigh(x.T @ x)
    return v[:, np.argsort(w)[::-1][:n]].T


def _heldout_matrix(x: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Every bead's held-out error at every basis size (K, I_max), for a model (PCA and
    thin-plate field) learnt on all rows of ``x`` (K, S)."""
    n_max = min(GAIN_COMPONENTS, max(1, (len(x) - 2) // 2), min(x.shape))
    vt = _leading(x, n_max)
    norm2 = (x**2).sum(axis=1).mean()
    return heldout_basis_errors(x, vt, positions, per_bead=True) * norm2


def _at_best(err: np.ndarray, judged: np.ndarray) -> np.ndarray:
    """The ``judged`` beads' errors at the basis size where their mean is least."""
    e = err[judged]
    return e[:, int(np.argmin(e.mean(axis=0)))]


def held_out_gain(x: np.ndarray, positions: np.ndarray, keep: np.ndarray, *,
                  before: np.ndarray | None = None) -> bool:
    """Whether leaving out the beads not in ``keep`` lowers the held-out error of the
    kept beads near them beyond its spread: the paired differences of those beads' errors
    with and without the others average more than :data:`GAIN_SE` standard errors above
    zero. "Near" is each left-out bead's ``2 SURROUND_NEIGHBOURS`` nearest kept beads:
    the thin-plate field changes little farther away, and beads that do not change would
    only dilute the test. ``before``: the errors of the model of all rows
    (:func:`_heldout_matrix`), when already at hand."""
    kept_pos = positions[keep]
    n_near = min(2 * SURROUND_NEIGHBOURS, len(kept_pos))
    near = np.zeros(len(kept_pos), bool)
    near[np.unique(cKDTree(kept_pos).query(positions[~keep], k=n_near)[1])] = True
    judged = np.zeros(len(x), bool)
    judged[np.flatnonzero(keep)[near]] = True
    if before is None:
        before = _heldout_matrix(x, positions)
    d = _at_best(before, judged) - _at_best(_heldout_matrix(x[keep], kept_pos), near)
    if len(d) < 2:
        return False
    return bool(d.mean() > GAIN_SE * d.std(ddof=1) / np.sqrt(len(d)))


def judge_outliers(x: np.ndarray, vt: np.ndarray, positions: np.ndarray, n_test: int,
                   threshold: float, *, min_keep: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Beads whose patch is unlike the others', judged by one statistic each and
    rejected only for a held-out gain.

    Each bead's statistic is its relative held-out error at ``n_test`` components: its
    part outside them plus the difference between its coefficients and what the
    thin-plate field of the others predicts there (leave-one-out). It is standardized
    robustly (median, median absolute deviation) within its kind: beads that their
    neighbours surround (:func:`surrounded`), where the field is interpolated, and beads
    at the rim, where it is extrapolated and every bead's prediction errs more, so that
    the rim's legitimately steep field is not read as outliers. Beads beyond
    :data:`GROSS_Z` are rejected outright; the others above ``threshold`` are rejected as
    a set only where the held-out error of the beads near them falls without them
    (:func:`held_out_gain`); otherwise the worse half of them is tried, and so on.

    Parameters
    ----------
    x : ndarray of shape (K, n)
        The weighted patches (rows) of the PCA.
    vt : ndarray of shape (>= n_test, n)
        The PCA's leading directions.
    positions : ndarray of shape (K, 2)
    n_test : int
        Components the statistic is measured against.
    threshold : float
        Robust standard deviations above which a bead is a candidate.
    min_keep : int
        Fewest beads to keep (the basis's need); rejections that would leave fewer are
        not tried, and a kind of fewer beads is standardized on every bead's scale.

    Returns
    -------
    zscores : ndarray of shape (K,)
        Each bead's standardized statistic.
    inliers : ndarray of shape (K,), bool
    """
    beta = x @ vt[:n_test].T
    norm2 = np.maximum((x**2).sum(axis=1), 1e-300)
    off = np.maximum(norm2 - (beta**2).sum(axis=1), 0.0)
    inner = surrounded(positions)
    loo = ThinPlateSpline(positions, beta).loo_residuals
    stat = np.sqrt((off + (loo**2).sum(axis=1)) / norm2)
    z = np.empty(len(x))
    for kind in (inner, ~inner):
        ref = stat[kind] if np.count_nonzero(kind) >= min_keep else stat
        z[kind] = _robust_z(stat[kind], ref)
    inliers = z <= max(GROSS_Z, threshold)
    cand = np.flatnonzero((z > threshold) & inliers)
    cand = cand[np.argsort(-z[cand])]
    before = None
    while len(cand) and int(inliers.sum()) - len(cand) >= min_keep:
        keep = inliers.copy()
        keep[cand] = False
        if before is None:
            before = _heldout_matrix(x[inliers], positions[inliers])
        if held_out_gain(x[inliers], positions[inliers], keep[inliers], before=before):
            inliers = keep
            break
        cand = cand[:len(cand) // 2]
    return z, inliers


def size_by_heldout(per_bead: np.ndarray) -> int:
    """The basis size of least cross-validated error.

    Parameters
    ----------
    per_bead : ndarray of shape (K, I_max)
        Each bead's error at each basis size for a model learnt without it
        (:func:`crossvalidated_basis_errors`).

    Returns
    -------
    int
        The size ``I`` whose mean error is least. The errors are those of beads the
        model never saw, so a size that only fits the learning beads' noise raises them,
        and no margin is added: a margin of one or two standard errors stops early on
        images of a few faint beads, where every size's error is noisy.
    """
    err = np.asarray(per_bead, np.float64)
    return int(np.argmin(err.mean(axis=0))) + 1


def crossvalidated_basis_errors(x: np.ndarray, xn: np.ndarray, positions: np.ndarray,
                                n_max: int, *, folds: int = SIZE_FOLDS) -> np.ndarray:
    """Each bead's error at each basis size ``I = 1 .. n_max`` for a model learnt
    without it.

    The beads are dealt into ``folds`` folds (a fixed shuffle); for each fold the
    basis is the PCA of the other folds' patches and the coefficients at the fold's
    beads are predicted by the thin-plate field of the others' coefficients. Unlike the
    closed form of :func:`heldout_basis_errors`, whose basis has seen the held-out bead
    (its noise lowers its own error by a share that grows with the basis), nothing
    here has seen it.

    Parameters
    ----------
    x : ndarray of shape (K, n)
        Sum-normalised patches (support pixels only), whose errors are measured.
    xn : ndarray of shape (K, n)
        The same patches as the PCA weights them (its input rows).
    positions : ndarray of shape (K, 2)
    n_max : int
        Largest basis size.
    folds : int
        Number of folds (at most ``K``).

    Returns
    -------
    ndarray of shape (K, n_max)
        Squared errors relative to the mean squared patch norm.
    """
    check_halt()
    x = np.asarray(x, np.float64)
    k = len(x)
    folds = max(2, min(int(folds), k))
    order = np.random.default_rng(0).permutation(k)
    norm2 = (x**2).sum(axis=1)
    err = np.empty((k, n_max))

    def fold(test):
        train = np.setdiff1d(order, test)
        vt = np.zeros((n_max, x.shape[1]))
        lead = _leading(xn[train], n_max)
        vt[:len(lead)] = lead
        pred = ThinPlateSpline(positions[train], x[train] @ vt.T)(positions[test])
        return norm2[test, None] + np.cumsum(pred * (pred - 2 * (x[test] @ vt.T)), axis=1)

    # the folds on the pool of threads: their time is in LAPACK's GIL-free calls
    tests = [np.sort(order[f::folds]) for f in range(folds)]
    for test, e in zip(tests, map_threads(fold, tests), strict=True):
        err[test] = e
    return err / norm2.mean()


def heldout_basis_errors(x: np.ndarray, vt: np.ndarray, positions: np.ndarray, *,
                         per_bead: bool = False) -> np.ndarray:
    """Leave-one-bead-out error of the model for each basis size ``I = 1 .. len(vt)``.

    For bead ``m`` held out, its coefficients are predicted by the thin-plate splines
    fitted to the other beads (exact leave-one-out residuals of a linear smoother), and
    the error is that of the predicted PSF against the bead's patch. With an
    orthonormal basis it has the closed form
    ``||p_m||^2 - sum_{i<=I} beta_{m,i}^2 + sum_{i<=I} (beta_{m,i} - beta_hat_{-m,i})^2``.

    Parameters
    ----------
    x : ndarray of shape (K, n)
        Sum-normalised patches (support pixels only).
    vt : ndarray of shape (I_max, n)
        Orthonormal basis rows.
    positions : ndarray of shape (K, 2)

    per_bead : bool
        Return every bead's error rather than their mean.

    Returns
    -------
    ndarray of shape (I_max,), or (K, I_max) with ``per_bead``
        Mean squared error relative to the mean squared patch norm.
    """
    beta = x @ vt.T
    loo = ThinPlateSpline(positions, beta).loo_residuals
    norm2 = (x**2).sum(axis=1)
    err = (norm2[:, None] - np.cumsum(beta**2, axis=1) + np.cumsum(loo**2, axis=1)) / norm2.mean()
    return err if per_bead else err.mean(axis=0)


__all__ = ["GAIN_SE", "GROSS_Z", "JUDGE_COMPONENTS", "SIZE_FOLDS",
           "crossvalidated_basis_errors", "heldout_basis_errors", "held_out_gain",
           "judge_outliers", "size_by_heldout", "surrounded"]
