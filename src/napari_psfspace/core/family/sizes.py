"""The size ``I`` of a family's PSF basis, chosen from the data.

The Gavish-Donoho rule assumes white noise of one level. The family's patches are
Wiener-filtered and their noise varies from bead to bead: on faint stacks the rule on
them keeps dozens of PSF components, most of them noise, and the family's operators are
worse than each image's own (``bench/bench_subspace.py --noise``). :func:`white_rank`
applies the rule to the raw patches whitened by each bead's noise instead: fewer
components the fainter the stack, and the family beats one image at a time there.

Tried, not kept: choosing ``I`` and ``J`` by 5-fold cross-validation over each image's
beads (the closed-form held-out residual of ``Gamma_k a(x)`` inside the cone, amplitude
fitted). It chose too small a model wherever an image has few beads (``I = J = 1`` on
7-bead images): taking one bead of six out changes an image's maps more than the sizes
do. ``J`` by cross-validation was worse than the rule on the maps on most stacks
(``bench/bench_subspace.py``).
"""

from __future__ import annotations

import numpy as np

from ..common.threads import map_threads
from ..model.pca import rank_by_threshold, singular_values


def white_rank(psf: np.ndarray, noise_sd: np.ndarray, window: np.ndarray, *,
               core: float = 0.5) -> int:
    """Gavish-Donoho rank of the patches whitened by their noise.

    Parameters
    ----------
    psf : ndarray of shape (N, P, P)
        Raw (not denoised) windowed sum-1 patches.
    noise_sd : ndarray of shape (N,)
        Per-pixel noise of each patch (the image's noise over the bead's flux).
    window : ndarray of shape (P, P)
        The window the patches were multiplied by.
    core : float
        Only pixels where the window exceeds this enter (the noise there is
        ``noise_sd * window``, divided out).

    Returns
    -------
    int
        Number of singular values of the whitened patches above the rule's threshold.
    """
    sel = np.asarray(window) > core
    sd = np.asarray(noise_sd, float).copy()
    good = np.isfinite(sd) & (sd > 0)
    if not good.any():  # no noise measured (e.g. a flat 8-bit background): unwhitened
        sd[:] = 1.0
    else:  # a bead whose background's MAD is 0 takes the typical noise
        sd[~good] = np.median(sd[good])
    x = psf[:, sel] / (sd[:, None] * window[sel])
    return rank_by_threshold(singular_values(x), x.shape)[0]


#: Basis size the whitened rule is trusted up to; beyond it, only as far as held-out
#: beads confirm (:func:`confirmed_size`): on a measured confocal stack the rule kept
#: noise the whitening does not model as PSFs.
RULE_TRUSTED = 12


def leading_directions(x: np.ndarray, n: int) -> np.ndarray:
    """The first ``n`` right singular vectors (n, S) of ``x`` (N, S), from the leading
    eigenvectors of its smaller Gram matrix (only they are wanted: a full SVD of a
    family's pooled patches computes hundreds more)."""
    from scipy.linalg import eigh

    n_rows, n_cols = x.shape
    n = max(1, min(int(n), n_rows, n_cols))
    if n_cols <= n_rows:
        _, vecs = eigh(x.T @ x, subset_by_index=[n_cols - n, n_cols - 1])
        return vecs[:, ::-1].T
    vals, vecs = eigh(x @ x.T, subset_by_index=[n_rows - n, n_rows - 1])
    vals, vecs = vals[::-1], vecs[:, ::-1]
    keep = vals > 0
    return (vecs[:, keep].T @ x) / np.sqrt(vals[keep])[:, None]


def confirmed_size(psf: list[np.ndarray], centers: list[np.ndarray], support: np.ndarray,
                   n_max: int, *, min_beads: int = 4) -> int:
    """The basis size the held-out beads support, at most ``n_max``.

    The pooled patches' principal directions (each patch l2-normalised); for each image
    with at least ``min_beads`` beads, each bead is predicted from the others by the
    image's own thin-plate field of its coefficients
    (:func:`~napari_psfspace.core.model.outliers.heldout_basis_errors`); the smallest size
    within 1 % of the lowest mean error over every such bead. ``n_max`` where no image
    has enough beads.

    Parameters
    ----------
    psf : list of ndarray, each of shape (N_k, P, P)
        Each image's sum-1 patches.
    centers : list of ndarray, each of shape (N_k, 2)
        Their positions.
    support : ndarray of shape (P, P), bool
        The window's support.
    n_max : int
    """
    from ..model.outliers import heldout_basis_errors

    x = np.concatenate([p[:, support] for p in psf])
    xn = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-300)
    vt = leading_directions(xn, int(n_max))
    def image_errors(item):
        p, c = item
        xi = p[:, support]
        scale = float((xi ** 2).sum(axis=1).mean())  # back to one scale for all
        return heldout_basis_errors(xi, vt, c, per_bead=True) * scale

    # one thin-plate fit an image, in LAPACK's GIL-free calls: on the pool of threads
    errors = map_threads(image_errors, [(p, c) for p, c in zip(psf, centers, strict=True)
                                        if len(p) >= min_beads])
    if not errors:
        return int(n_max)
    curve = np.concatenate(errors).mean(axis=0)
    return int(np.flatnonzero(curve <= 1.01 * curve.min())[0]) + 1


def family_sizes(used, n_psf: int | None, n_space: int | None, n_images: int, *,
                 min_beads: int) -> tuple[int, dict]:
    """The basis size ``I`` and how it was chosen: given, or the rank rule on the patches
    whitened by their noise, bounded by what the beads support, and beyond
    :data:`RULE_TRUSTED` only as far as held-out beads confirm (:func:`confirmed_size`,
    each image's maps from at least ``min_beads`` beads); ``J`` is left to the rule on
    the maps where not given."""
    from ..beads.window import bump_window, radial_distance

    sizes_meta: dict = {"psf_size_by": "fixed", "space_size_by": "fixed"}
    if n_psf is None:
        first = used[0].patches
        window = bump_window(first.size, first.r, first.r_ext)
        n_psf = min(white_rank(np.concatenate([f.patches.psf for f in used]),
                               np.concatenate([f.patches.noise / f.patches.flux for f in used]),
                               window),
                    max(1, (sum(f.n_beads for f in used) - 2) // 2))
        sizes_meta["psf_size_by"] = "whitened rule"
        if n_psf > RULE_TRUSTED:  # beyond it, as far as the held-out beads confirm
            confirmed = confirmed_size([f.patches.psf for f in used],
                                       [f.patches.centers for f in used],
                                       radial_distance(first.size) < first.r_ext, n_psf,
                                       min_beads=min_beads)
            sizes_meta["psf_size_rule"] = int(n_psf)
            n_psf = max(RULE_TRUSTED, min(n_psf, confirmed))
            sizes_meta["psf_size_by"] = "whitened rule, beyond 12 as held-out beads confirm"
        if n_space is not None and n_space > n_images * n_psf:
            raise ValueError(f"`n_space` = {n_space} is more spatial maps than {n_images} "
                             f"images of {n_psf} PSFs (chosen from the beads) give: at most "
                             f"{n_images * n_psf}")
    if n_space is None:
        sizes_meta["space_size_by"] = "rule"
    return n_psf, sizes_meta
