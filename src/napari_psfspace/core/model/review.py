"""Numbers behind the patch review: per-bead views and flags.

The review shows every bead whose patch fits in the image in three views (raw,
background removed, windowed) with the reasons it may be a bad PSF sample: a z-score
outlier of the PCA (paper, App. A), a neighbour closer than ``2 r``, saturated pixels.
Pure numpy / scipy; a GUI only displays :class:`PatchReview`.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..beads.centering import gather_windows, refine_centers
from ..beads.detect import BORDER, KEPT, NEIGHBOUR_RATIO, STRUCTURE, Beads
from ..beads.overlap import NEIGHBOUR_SHARE, patch_shares
from ..beads.patches import extract_patches
from ..beads.window import bump_window, radial_distance
from ..common.progress import Progress
from ..common.spacing import bead_border, centring_sigma, min_separation
from ..common.threads import blas_threads
from ..common.validate import as_image, check_psf_radius
from .pca import learn_basis, min_beads_for

#: The three views of a patch, in display order.
VIEWS = ("raw", "background removed", "windowed")


@dataclass
class PatchReview:
    """Patches of the reviewable beads, their views and flags.

    Attributes
    ----------
    index : ndarray of shape (K,), int
        Index into the :class:`~napari_psfspace.core.beads.detect.Beads` table of each patch.
    centers : ndarray of shape (K, 2)
        Sub-pixel centres (row, column) in pixels the patches are re-sampled on.
    views : dict of str to ndarray of shape (K, P, P)
        ``"raw"`` (image units), ``"background removed"`` (raw minus the fitted
        background) and ``"windowed"`` (background removed times the bump
        window), keys :data:`VIEWS`.
    zscore : ndarray of shape (K,)
        The bead's held-out error among the kept beads' in robust standard deviations
        (:func:`~napari_psfspace.core.model.outliers.judge_outliers`; NaN for a bead
        that is not kept, or when there are too few kept beads).
    outlier : ndarray of shape (K,), bool
        Left out by that judge (above ``z_threshold`` and with a held-out gain, or
        grossly off).
    neighbour : ndarray of shape (K,), bool
        Another bead (any status) lies closer than ``2 r``.
    saturated : ndarray of shape (K,), bool
        The bead's core touches the saturation level.
    """

    index: np.ndarray
    centers: np.ndarray
    views: dict[str, np.ndarray]
    zscore: np.ndarray
    outlier: np.ndarray
    neighbour: np.ndarray
    saturated: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    def flags(self, k: int) -> list[str]:
        """Human-readable flags of patch ``k`` (empty when it looks clean)."""
        out = []
        if self.outlier[k]:
            out.append(f"outlier (held-out error z = {self.zscore[k]:.1f})")
        if self.neighbour[k]:
            out.append("neighbour closer than 2 r")
        if self.saturated[k]:
            out.append("saturated")
        return out


@blas_threads
def iter_patch_review(
    image,
    beads: Beads,
    psf_radius: float,
    *,
    z_threshold: float = 3.0,
    saturation: float | None = None,
) -> Generator[Progress, None, PatchReview]:
    """Extract and flag the patches of every bead that fits in the image.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Bead image, any real dtype.
    beads : Beads
        Beads to review (e.g. edited by hand); beads with status ``border`` or whose
        window leaves the image are skipped.
    psf_radius : float
        PSF radius ``r`` in pixels.
    z_threshold : float
        z-score above which a kept bead is flagged as an outlier (paper: 3).
    saturation : float, optional
        Saturation level; default the dtype maximum for integer images.

    Yields
    ------
    Progress

    Returns
    -------
    PatchReview

    Raises
    ------
    ValueError
        No bead of ``beads`` fits in the image.
    """
    raw = np.asarray(image)
    img = as_image(raw)
    r = check_psf_radius(psf_radius, img.shape)
    if saturation is None and raw.dtype.kind in "ui":
        saturation = float(np.iinfo(raw.dtype).max)
    pos = beads.positions
    h, w = img.shape
    margin = bead_border(r)
    inside = ((pos[:, 0] >= margin) & (pos[:, 1] >= margin) & (pos[:, 0] <= h - 1 - margin)
              & (pos[:, 1] <= w - 1 - margin))
    index = np.flatnonzero(inside & (beads.status != BORDER))
    if len(index) == 0:
        raise ValueError(
            f"None of the {len(beads)} beads lies at least {margin:g} px from the border: "
            "nothing to review. Detect beads first, or lower `psf_radius`."
        )
    centers = refine_centers(img, pos[index], sigma=centring_sigma(r), half=int(np.ceil(r)))
    yield Progress("centre", 0.3, f"{len(index)} beads centred")
    patches = extract_patches(img, centers, r)
    signal = patches.raw - patches.background
    views = {"raw": patches.raw, "background removed": signal,
             "windowed": signal * bump_window(patches.size, r, patches.r_ext)}
    yield Progress("patches", 0.6, f"{len(index)} patches of {patches.size} px")

    zscore = np.full(len(index), np.nan)
    outlier = np.zeros(len(index), bool)
    kept = (beads.status[index] == KEPT) & (patches.flux > 0)
    if np.count_nonzero(kept) >= min_beads_for(1):
        support = radial_distance(patches.size) < patches.r_ext
        basis = learn_basis(patches.psf[kept], "rule", support=support,
                            positions=patches.centers[kept], z_threshold=z_threshold)
        zscore[kept] = basis.zscores
        outlier[kept] = ~basis.inliers

    neighbour = np.zeros(len(index), bool)
    if len(pos) > 1:  # the estimate's rule: the light the others add to the patch
        real = np.flatnonzero(beads.status != STRUCTURE)
        share = patch_shares(img, pos, index, real, r,
                             neighbour_ratio=NEIGHBOUR_RATIO)
        if share is not None:
            neighbour = share >= NEIGHBOUR_SHARE
        else:
            dist, _ = cKDTree(pos).query(pos[index], k=2)
            neighbour = dist[:, 1] < min_separation(r)
    saturated = np.zeros(len(index), bool)
    if saturation is not None:
        core = gather_windows(raw, pos[index], max(1, int(round(r / 3))))
        saturated = core.reshape(len(index), -1).max(axis=1) >= saturation
    yield Progress("flags", 1.0, f"{int(outlier.sum())} outliers, "
                                 f"{int(neighbour.sum())} with a neighbour, "
                                 f"{int(saturated.sum())} saturated")
    return PatchReview(index, centers, views, zscore, outlier, neighbour, saturated)


def patch_review(image, beads: Beads, psf_radius: float, **kwargs) -> PatchReview:
    """:func:`iter_patch_review` run to completion; same parameters."""
    gen = iter_patch_review(image, beads, psf_radius, **kwargs)
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value


__all__ = ["VIEWS", "PatchReview", "iter_patch_review", "patch_review"]
