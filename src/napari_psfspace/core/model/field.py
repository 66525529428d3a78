"""The coefficient field of a PSF basis over the image, and the operator it makes.

Paper, sec. 2.3 and App. C: each bead's PSF coefficients are interpolated over the field
(weighted thin-plate splines, :func:`fit_field`, or any field function), evaluated on a
coarse grid, projected onto the cone of the observed coefficients and normalised so that
every PSF sums to 1 (:func:`assemble_operator`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..beads.patches import Patches
from .cone import Cone, reduce_cone
from .operator import ProductConvolution
from .pca import PsfBasis
from .psf_field import interp_weights
from .tps import ThinPlateSpline
from .voronoi import voronoi_areas


def coarse_grid(shape: tuple[int, int], step: float) -> tuple[np.ndarray, np.ndarray]:
    """Node coordinates spanning the image with spacing at most ``step`` pixels."""
    nodes = [np.linspace(0.0, n - 1.0, max(2, int(np.ceil((n - 1) / step)) + 1)) for n in shape]
    return nodes[0], nodes[1]


def fit_field(
    basis: PsfBasis,
    patches: Patches,
    shape: tuple[int, int],
    *,
    smoothing=None,
    grid_step: float = 32.0,
    metadata: dict | None = None,
    basis_filter: Callable[[np.ndarray], np.ndarray] | None = None,
    refit: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[ProductConvolution, Cone, ThinPlateSpline]:
    """Interpolate the PSF coefficients over the field and build the operator.

    Parameters
    ----------
    basis : PsfBasis
        PSF basis and the coefficients of the inlier patches.
    patches : Patches
        The patches the basis was learnt from (``basis.inliers`` selects the inliers).
    shape : tuple of int
        Image shape (rows, columns).
    smoothing : float or None
        Thin-plate smoothing ``eta``; ``None`` chooses it per coefficient by GCV.
    grid_step : float
        Spacing in pixels of the coarse grid on which the maps are evaluated (they are
        bilinear in between, which keeps them in the cone).
    basis_filter : callable, optional
        ``basis_filter(h) -> h'``, shape (I, P, P): a linear change of every PSF of the
        model (e.g. removing the beads' size,
        :func:`~napari_psfspace.core.beads.sphere.remove_sphere`),
        applied before the maps are normalised so that every PSF still sums to 1.
    refit : callable, optional
        ``refit(a) -> h``: new basis images (I, P, P) given the fitted field at the
        inlier beads, shape (K_in, I) (e.g.
        :func:`~napari_psfspace.core.model.denoise.refit_basis` against the raw patches).

    Returns
    -------
    operator, cone, spline
    """
    centers = patches.centers[basis.inliers]
    beta = basis.coefficients
    weights = voronoi_areas(centers, shape)
    spline = ThinPlateSpline(centers, beta, weights=weights, smoothing=smoothing,
                             scale=0.5 * float(np.hypot(*shape)))
    images = basis.basis if refit is None else refit(spline(centers).reshape(len(centers), -1))
    op, cone = assemble_operator(images, beta, spline, shape, grid_step=grid_step,
                                 metadata=metadata, basis_filter=basis_filter)
    return op, cone, spline


def assemble_operator(
    basis: np.ndarray,
    beta: np.ndarray,
    field: Callable[[np.ndarray], np.ndarray],
    shape: tuple[int, int],
    *,
    grid_step: float = 32.0,
    metadata: dict | None = None,
    basis_filter: Callable[[np.ndarray], np.ndarray] | None = None,
    cone: Cone | None = None,
    at: np.ndarray | None = None,
) -> tuple[ProductConvolution, Cone]:
    """The operator of a basis and a coefficient field, kept inside the cone.

    Parameters
    ----------
    basis : ndarray of shape (I, P, P)
    beta : ndarray of shape (M, I)
        Observed coefficients of the beads (they span the cone).
    field : callable
        ``field(nodes) -> (G, I)``: the coefficients at positions (G, 2) (row, column).
    shape : tuple of int
    grid_step, metadata, basis_filter
        As in :func:`fit_field`.
    cone : Cone, optional
        The cone to keep the field in; default :func:`reduce_cone` of ``beta`` (at most
        20 generators: one image's PSFs).
    at : ndarray of shape (n, 2), optional
        Only the PSFs at these positions (row, column) will be asked for: only the
        nodes around them are kept in the cone (the projection is the costly step), and
        the operator is right only there. For judging a model on a few beads.

    Returns
    -------
    operator, cone
    """
    gy, gx = coarse_grid(shape, grid_step)
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    coarse = np.asarray(field(nodes), dtype=np.float64).reshape(len(nodes), -1)  # (G, I)
    cone = reduce_cone(beta) if cone is None else cone
    if at is None:
        coarse = cone.project(coarse)
    else:
        pts = np.asarray(at, dtype=np.float64).reshape(-1, 2)
        j0, j1, _ = interp_weights(gy, pts[:, 0])
        k0, k1, _ = interp_weights(gx, pts[:, 1])
        near = np.unique(np.concatenate([j * len(gx) + k for j in (j0, j1) for k in (k0, k1)]))
        coarse[near] = cone.project(coarse[near])
    psfs = basis if basis_filter is None else basis_filter(basis)
    sums = psfs.sum(axis=(1, 2))  # (I,)
    total = coarse @ sums
    bad = total <= 1e-12 * np.abs(coarse).sum(axis=1).clip(1e-300)
    if bad.any():  # projected to the apex: fall back to the mean observed PSF
        mean = beta.mean(axis=0)
        coarse[bad] = mean
        total[bad] = mean @ sums
    coarse = coarse / total[:, None]
    maps = coarse.T.reshape(len(basis), len(gy), len(gx))
    op = ProductConvolution(psfs, maps, shape=shape, grid=(gy, gx), metadata=metadata)
    return op, cone
