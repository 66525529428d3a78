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
from .cone import Cone, full_cone, implausible, reduce_cone
from .operator import ProductConvolution
from .pca import PsfBasis
from .psf_field import interp_weights
from .tps import ThinPlateSpline
from .voronoi import voronoi_areas

#: Default of :func:`assemble_operator`'s ``constraint``: the paper kept every node in a
#: cone of at most 20 generators; on wide strongly aberrated fields that cone cost much of
#: the field error, and the field needs it only where its PSFs turn implausible
#: (``bench/bench_caps.py``).
CONSTRAINT = "where-needed"


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
    constraint: str | None = None,
    at: np.ndarray | None = None,
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
        Thin-plate smoothing ``eta``; ``None`` chooses it per coefficient by leave-one-out.
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
    constraint : {"where-needed", "cone", "none"}, optional
        As :func:`assemble_operator`'s. Default: chosen by the beads held out one at a
        time (:func:`choose_constraint`), between "where-needed" and the paper's "cone";
        the choice and both held-out errors go to ``metadata["field_constraint"]``.
    at : ndarray of shape (n, 2), optional
        As :func:`assemble_operator`'s: the operator is right only at these positions
        (row, column), for judging the field on a few held-out beads.

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
    if constraint is None:
        psfs = images if basis_filter is None else basis_filter(images)
        loo = np.asarray(spline.loo_residuals).reshape(beta.shape)
        constraint, scores = choose_constraint(beta, beta - loo, psfs)
        metadata = {**(metadata or {}), "field_constraint": {"chosen": constraint, **scores}}
    op, cone = assemble_operator(images, beta, spline, shape, grid_step=grid_step,
                                 metadata=metadata, basis_filter=basis_filter,
                                 constraint=constraint, at=at)
    return op, cone, spline


def choose_constraint(beta: np.ndarray, predicted: np.ndarray, psfs: np.ndarray
                      ) -> tuple[str, dict[str, float]]:
    """Where to keep the field in the cone, as the held-out beads say.

    Parameters
    ----------
    beta : ndarray of shape (M, I)
        The beads' coefficients.
    predicted : ndarray of shape (M, I)
        Each bead's coefficients as the field predicts them without it (leave-one-out).
    psfs : ndarray of shape (I, P, P)
        The basis images (for the PSFs' negative mass).

    Returns
    -------
    constraint : {"where-needed", "cone"}
        "cone" (the paper's reduced cone everywhere) only where it brings the held-out
        beads' predictions closer to their coefficients: the field is never worse than
        the paper's on them.
    scores : dict
        Mean squared error of the held-out predictions under each (``"where-needed"``,
        ``"cone"``).
    """
    beta = np.asarray(beta, dtype=np.float64)
    pred = np.asarray(predicted, dtype=np.float64)
    sums = np.asarray(psfs, dtype=np.float64).reshape(len(psfs), -1).sum(axis=1)

    def err(c):
        tot = c @ sums
        ok = np.abs(tot) > 1e-12
        c = np.where(ok[:, None], c / np.where(ok, tot, 1.0)[:, None], c)
        ref = beta / (beta @ sums)[:, None]
        return float(np.mean(np.sum((c - ref) ** 2, axis=1)))

    where = pred.copy()
    bad = implausible(pred, psfs, beta)
    if bad.any():
        where[bad] = full_cone(beta).project(pred[bad])
    scores = {"where-needed": err(where), "cone": err(reduce_cone(beta).project(pred))}
    # equal up to rounding (nothing projected differently): the lighter rule
    better = scores["cone"] < scores["where-needed"] * (1 - 1e-9) - 1e-300
    return ("cone" if better else "where-needed"), scores


def keep_in_cone(coarse: np.ndarray, beta: np.ndarray, psfs: np.ndarray,
                 constraint: str) -> tuple[np.ndarray, Cone]:
    """Coefficients (G, I) kept in the cone of the beads' ``beta`` (M, I) as
    ``constraint`` says ("where-needed": only those whose PSF, ``coarse @ psfs``, has
    more negative mass than the beads' own allow, onto the hull of every bead; "cone":
    all, onto the paper's reduced cone; "none": none), and that cone."""
    out = np.array(coarse, dtype=np.float64)
    cone = reduce_cone(beta) if constraint == "cone" else full_cone(beta)
    if constraint == "cone":
        out = cone.project(out)
    elif constraint == "where-needed":
        bad = implausible(out, psfs, beta)
        if bad.any():
            out[bad] = cone.project(out[bad])
    return out, cone


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
    constraint: str | None = None,
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

    constraint : {"where-needed", "cone", "none"}, optional
        Where the field is kept in the cone. "where-needed" (default, or
        :data:`CONSTRAINT`): only at nodes whose PSF has more negative mass than the
        beads' own allow (:func:`~.cone.implausible`), onto the hull of every bead's
        coefficients; "cone": every node, onto ``cone`` or the reduced cone of at most
        20 generators (the paper's rule); "none": nowhere.

    Returns
    -------
    operator, cone
    """
    constraint = CONSTRAINT if constraint is None else constraint
    if constraint not in ("where-needed", "cone", "none"):
        raise ValueError(f"`constraint` must be 'where-needed', 'cone' or 'none', got "
                         f"{constraint!r}.")
    gy, gx = coarse_grid(shape, grid_step)
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    coarse = np.asarray(field(nodes), dtype=np.float64).reshape(len(nodes), -1)  # (G, I)
    psfs = basis if basis_filter is None else basis_filter(basis)
    if cone is None:
        cone = reduce_cone(beta) if constraint == "cone" else full_cone(beta)
    if at is None:
        near = np.arange(len(coarse))
    else:
        pts = np.asarray(at, dtype=np.float64).reshape(-1, 2)
        j0, j1, _ = interp_weights(gy, pts[:, 0])
        k0, k1, _ = interp_weights(gx, pts[:, 1])
        near = np.unique(np.concatenate([j * len(gx) + k for j in (j0, j1) for k in (k0, k1)]))
    if constraint == "where-needed":
        near = near[implausible(coarse[near], psfs, beta)]
    if constraint != "none" and len(near):
        coarse[near] = cone.project(coarse[near])
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
