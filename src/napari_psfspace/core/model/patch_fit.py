"""One image's operator from its bead patches: PCA, thin-plate field, cone (sec. 2.3).

The fitting half of :func:`~napari_psfspace.core.model.estimate.iter_estimate`, once the
beads are found, centred and cut out; the family
(:func:`~napari_psfspace.core.family.estimate_family`) calls it too, on each image's
own patches, for the single-image estimate each image's family operator must not lose to.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..beads.patches import Patches
from ..beads.window import bump_window, radial_distance
from .cone import Cone
from .denoise import band_limit, refit_basis
from .field import fit_field
from .operator import ProductConvolution
from .pca import PsfBasis, learn_basis
from .tps import ThinPlateSpline


def fit_patches(
    patches: Patches,
    shape: tuple[int, int],
    *,
    n_psf: int | str | None = None,
    smoothing: float | None = None,
    grid_step: float = 32.0,
    z_threshold: float = 3.0,
    denoise: bool = True,
    basis_filter: Callable[[np.ndarray], Callable | None] | None = None,
    record: dict | None = None,
    at: np.ndarray | None = None,
) -> tuple[PsfBasis, ProductConvolution, Cone, ThinPlateSpline]:
    """PSF basis, field and operator of one image's usable bead patches.

    Parameters
    ----------
    patches : Patches
        The image's usable beads (at least ``min_beads_for(n_psf)``).
    shape : tuple of int
        Image shape (rows, columns).
    n_psf, smoothing, grid_step, z_threshold, denoise
        As in :func:`~napari_psfspace.core.model.estimate.estimate_operator`.
    basis_filter : callable, optional
        ``basis_filter(psf) -> filter or None``: given the inlier beads' patches (K, P,
        P), the ``basis_filter`` of :func:`~napari_psfspace.core.model.field.fit_field`
        (e.g. removing the beads' size).
    record : dict, optional
        Filled with the denoising's record (passband, basis noise).
    at : ndarray of shape (n, 2), optional
        Only the PSFs at these positions (row, column) will be asked for
        (:func:`~napari_psfspace.core.model.field.assemble_operator`'s ``at``).

    Returns
    -------
    basis : PsfBasis
    operator : ProductConvolution
    cone : Cone
    spline : ThinPlateSpline
    """
    record = {} if record is None else record
    support = radial_distance(patches.size) < patches.r_ext
    window = bump_window(patches.size, patches.r, patches.r_ext)
    learn, weights, refit = patches.psf, None, None
    if denoise:
        sd = patches.noise / patches.flux  # per-pixel noise of the sum-1 patches
        weights = 1.0 / (patches.psf[:, support] ** 2).sum(axis=1)
        learn, info = band_limit(patches.psf, sd, window)
        record.update(info)
    basis = learn_basis(learn, n_psf, support=support, positions=patches.centers,
                        z_threshold=z_threshold, weights=weights)
    if denoise and not basis.inliers.all():
        # the learning filter again without the outliers: a gross one (a hot pixel the
        # detector missed in a bead's core) fills the patches' mean power spectrum with
        # noise that the filter would then let through on every bead
        inl = basis.inliers
        learn, info = band_limit(patches.psf[inl], sd[inl], window)
        record.update(info)
        again = learn_basis(learn, n_psf, support=support, positions=patches.centers[inl],
                            z_threshold=np.inf, weights=weights[inl])
        basis = PsfBasis(again.basis, again.coefficients, inl, basis.zscores,
                         again.singular_values, again.rank_threshold, again.n_psf_rule,
                         again.heldout_errors, again.components)
    if denoise:
        inl = basis.inliers

        def refit(a):
            h, info = refit_basis(patches.psf[inl], a, sd[inl], window, weights=weights[inl],
                                  prior=basis.basis)
            record.update(info)
            return h
    filt = None if basis_filter is None else basis_filter(patches.psf[basis.inliers])
    op, cone, spline = fit_field(basis, patches, shape, smoothing=smoothing,
                                 grid_step=grid_step, basis_filter=filt, refit=refit, at=at)
    return basis, op, cone, spline
