"""A space-varying 3D PSF from a bead z-stack (the paper's extension to 3D).

detect on the best-focus slice -> centre laterally -> each bead's own focus and the
field's focal surface through them (:mod:`~napari_psfspace.core.volume.focal_surface`;
beads far off it are left out, ``off-focus``) -> 3D patches about the bead plane (the
beads' median focus), each moved along z onto the surface
(:mod:`~napari_psfspace.core.volume.patches3d`) -> PCA of the 3D patches with the 2D
estimator's outlier rejection -> the same weighted thin-plate field over (row, column)
-> the cone of the observed coefficients ->
:class:`~napari_psfspace.core.volume.operator3d.ProductConvolution3D`.

A bead's scatter about the surface (beads at different depths) is taken out before the
PCA, so that it does not widen the PSF; the surface itself (field curvature, a tilted
focus) stays in the operator, which a deconvolution needs.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass, field
from operator import attrgetter

import numpy as np

from ..beads.detect import FAINT, KEPT, OFF_FOCUS, OUTLIER, Beads, NoBeadsError, detect_beads
from ..beads.focus import bead_peaks, best_focus_index
from ..beads.saturation import saturation_record
from ..beads.window import radial_distance
from ..common.progress import Progress, wait_with_progress, within
from ..common.threads import blas_threads
from ..common.twins import drained
from ..common.validate import (
    as_stack,
    check_grid_step,
    check_int,
    check_psf_radius,
    check_signal,
)
from ..model.cone import Cone, reduce_cone
from ..model.estimate import centre_beads, faint_beads
from ..model.field import choose_constraint, coarse_grid, keep_in_cone
from ..model.pca import PsfBasis, learn_basis, min_beads_for
from ..model.tps import ThinPlateSpline
from ..model.voronoi import voronoi_areas
from .focal_surface import (
    FocalSurface,
    axial_centres,
    fit_focal_surface,
    focus_line,
    focus_record,
)
from .heldout3d import FOLDS, Heldout3D, iter_heldout_error_3d
from .operator3d import ProductConvolution3D
from .patches3d import Patches3D, extract_patches_3d

#: Fewest kept beads whose median plane of best focus sets the bead plane.
MIN_PLANE_VOTES = 5


@dataclass
class Estimation3D:
    """What :func:`iter_estimate_operator_3d` produced.

    Attributes
    ----------
    operator : ProductConvolution3D
    beads : Beads
        Every detection on the best-focus slice with its status.
    patches : Patches3D
        The patches that entered the PCA (their order: ``patch_index``).
    patch_index : ndarray of shape (K,)
        Index into ``beads`` of each patch.
    basis : PsfBasis
    cone : Cone
    bead_focus : ndarray of shape (K,)
        Each patch's bead's own focus, planes from the first, sub-plane (NaN: its axial
        profile's half maximum is not reached inside the stack).
    surface : FocalSurface
        The field's focal surface through the beads' foci; each patch is moved along z
        by its bead's offset from it (``surface.offsets``) before the PCA.
    """

    operator: ProductConvolution3D
    beads: Beads
    patches: Patches3D
    patch_index: np.ndarray
    basis: PsfBasis
    cone: Cone
    bead_focus: np.ndarray
    surface: FocalSurface
    info: dict = field(default_factory=dict)
    heldout: Heldout3D | None = None


def bead_stack(stack) -> np.ndarray:
    """A bead z-stack as float32 (Z, H, W), checked by the stacks' validator: three
    dimensions, at least 3 planes of at least 8 x 8 pixels, real and finite values."""
    vol = np.asarray(as_stack(stack, min_planes=3, min_side=8, copies=6), dtype=np.float32)
    check_signal(vol, "stack")
    return vol


@blas_threads
def iter_estimate_operator_3d(
    stack,
    *,
    psf_radius: float,
    z_radius: int | None = None,
    bead_diameter: float = 0.0,
    n_psf: int | str | None = None,
    smoothing: float | None = None,
    threshold: float = 8.0,
    grid_step: float = 32.0,
    z_threshold: float = 3.0,
    voxel_size: tuple[float, float, float] | None = None,
    holdout: bool = True,
) -> Generator[Progress, None, Estimation3D]:
    """Learn the space-varying 3D PSF of a microscope from a z-stack of beads on a
    coverslip.

    Parameters
    ----------
    stack : array_like of shape (Z, H, W)
        The same bead field at Z focus positions, any real dtype.
    psf_radius : float
        ``r``, pixels: the PSF's lateral radius on the widest plane used (beyond it,
        background only).
    z_radius : int, optional
        Planes kept on each side of the bead plane; default all the stack's.
    bead_diameter : float
        Must be 0 (point sources): the bead's sphere is not divided out in 3D yet.
    n_psf : int, "heldout", "rule" or None
        Basis size, as in :func:`~napari_psfspace.core.model.estimate.estimate_operator`.
    smoothing : float, optional
        Thin-plate smoothing; default by leave-one-out.
    threshold : float
        Detection threshold on the best-focus slice, noise sd.
    grid_step : float
        Spacing of the maps' coarse grid, pixels.
    z_threshold : float
        Outlier rejection of the PCA, standard deviations.
    voxel_size : (float, float, float), optional
        ``(dz, dy, dx)``, µm (from the file: ``napari_psfspace.io``).
    holdout : bool
        Score the field on held-out beads against one 3D PSF
        (:func:`~napari_psfspace.core.volume.heldout3d.heldout_error_3d`, with 10 beads or
        more): ``metadata["heldout"]``; where one PSF does better, the model is that one
        PSF (``field_model`` says so, and why).

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    Estimation3D
        The operator, the beads, patches, basis, cone, foci and focal surface it was
        learnt from.
    Raises
    ------
    ValueError
        A bad argument, or :class:`~napari_psfspace.core.beads.detect.NoBeadsError` (too
        few usable beads).
    """
    vol = bead_stack(stack)
    depth, h, w = vol.shape
    r = check_psf_radius(psf_radius, (h, w))
    grid_step = check_grid_step(grid_step, (h, w))
    if bead_diameter:
        raise ValueError(f"`bead_diameter` = {bead_diameter!r}: dividing a bead's sphere out "
                         "of a 3D PSF is not implemented yet; give 0 (point sources)")
    focus, beads, kept = yield from _detect(stack, threshold, vol, r)
    foci, plane, z_radius, surface, kept, patches, need = yield from _patches_3d(
            z_radius, n_psf, voxel_size, vol, (depth, h, w), r, focus, beads, kept)
    if len(kept) < need:  # a bead or a few: one 3D PSF for the whole field, their mean
        return (yield from _one_psf(stack, vol, beads, patches, kept, foci, surface, plane,
                                    z_radius, r, threshold, grid_step, voxel_size, focus))

    inside = patches.data_planes(depth)
    support = (inside[:, None, None]
               & (radial_distance(patches.size) < patches.r_ext)[None])
    basis = yield from wait_with_progress(
        lambda: learn_basis(patches.psf, n_psf, support=support, positions=patches.centers,
                            z_threshold=z_threshold),
        Progress("basis", 0.5, "the PCA basis, outliers rejected"))
    beads.status[kept[~basis.inliers]] = OUTLIER
    yield Progress("basis", 0.7, f"{basis.n_psf} 3D PSFs from {int(basis.inliers.sum())} "
                   "beads")
    gx, gy, cone, coefficients, meta, op = _field_operator(
            stack, z_radius, smoothing, threshold, grid_step, voxel_size, (depth, h, w), r, focus,
            beads, foci, plane, surface, patches, basis)
    yield Progress("fit", 0.9, f"{basis.n_psf} 3D PSFs of {op.kernel_shape[0]} x "
                   f"{op.kernel_shape[1]} x {op.kernel_shape[2]} voxels from "
                   f"{meta['n_beads_used']} beads")
    est = Estimation3D(op, beads, patches, kept, basis, cone, foci, surface)
    yield from _held_out(stack, smoothing, voxel_size, holdout, (depth, h, w), plane, patches,
                         basis, gx, gy, coefficients, meta, est)
    return est


def _detect(stack, threshold, vol, r):
    """The best-focus slice, the beads detected there and centred laterally; the long steps
    run in a helper thread while this generator keeps answering (Cancel is honoured within a
    fraction of a second)."""
    # the long steps run in a helper thread while this generator keeps answering
    # (wait_with_progress): Cancel is honoured within a fraction of a second
    focus = yield from wait_with_progress(lambda: best_focus_index(vol),
                                          Progress("detect", 0.0, "best-focus slice"))
    beads = yield from wait_with_progress(
        lambda: detect_beads(np.asarray(stack)[focus], r, threshold=threshold),
        Progress("detect", 0.05, f"detecting beads on slice {focus}"))
    img = beads.clean_image(vol[focus])
    yield Progress("detect", 0.15, f"slice {focus} (best focus): {beads.summary()}")
    kept = centre_beads(img, beads, r)
    yield Progress("centre", 0.3, f"{len(kept)} beads centred laterally")
    return focus, beads, kept


def _patches_3d(z_radius, n_psf, voxel_size, vol, shape, r, focus, beads, kept):
    """Each bead's focus, the focal surface through them (the beads far off it left out),
    the plane and depth of the PSFs and the beads' 3D patches registered onto the surface;
    faint beads left out."""
    depth, h, w = shape
    peaks = yield from wait_with_progress(
        lambda: bead_peaks(vol, beads.positions[kept], r),
        Progress("patches", 0.35, "each bead's focus"))
    foci, widths = axial_centres(peaks)
    has = np.isfinite(foci)
    # the beads' median focus; a handful of beads cannot outvote the noise of one whose
    # profile has two maxima: the stack's best focus, from every detection, then
    plane = (int(np.round(np.median(foci[has]))) if has.sum() >= MIN_PLANE_VOTES
             else int(focus))
    if z_radius is None:
        z_radius = max(plane, depth - 1 - plane)
    # planes beyond the stack hold nothing: at most depth - 1 on each side
    z_radius = check_int(z_radius, "z_radius", minimum=1, maximum=max(depth - 1, 1))
    surface = fit_focal_surface(beads.positions[kept], foci, widths, (h, w), depth=depth)
    beads.status[kept[surface.off]] = OFF_FOCUS
    kept, foci = kept[~surface.off], foci[~surface.off]
    offsets = np.nan_to_num(surface.offsets[~surface.off])
    margin = int(np.ceil(np.abs(offsets).max())) if len(offsets) else 0
    yield Progress("patches", 0.38, focus_line(surface, voxel_size))
    patches = yield from wait_with_progress(
        lambda: extract_patches_3d(vol, beads.positions[kept], r, plane=plane,
                                   z_radius=z_radius + margin)
        .registered(offsets, margin, depth),
        Progress("patches", 0.4, "3D patches, each bead's focus onto the focal surface"))
    usable = patches.flux > 0
    faint, _ = faint_beads(np.where(usable, patches.flux, 0.0))
    usable &= ~faint
    beads.status[kept[~usable & (beads.status[kept] == KEPT)]] = FAINT
    kept, foci, patches = kept[usable], foci[usable], patches.subset(usable)
    need = min_beads_for(n_psf if isinstance(n_psf, int) else 1)
    if len(kept) == 0 or (len(kept) < need and isinstance(n_psf, int)):
        raise NoBeadsError(f"Too few usable beads for a 3D PSF: {len(kept)}, need at least "
                           f"{max(need, 1)}. {beads.summary()}")
    yield Progress("patches", 0.45, f"{len(kept)} patches of {len(patches.planes)} x "
                   f"{patches.size} x {patches.size} voxels about plane {plane}")
    return foci, plane, z_radius, surface, kept, patches, need


def _field_operator(stack, z_radius, smoothing, threshold, grid_step, voxel_size, shape, r,
                    focus, beads, foci, plane, surface, patches, basis):
    """The operator: the basis' coefficients over the field by a thin-plate spline on a
    coarse grid, kept in the cone where the beads held out one at a time say so (as for one
    image), with the metadata."""
    depth, h, w = shape
    centers = patches.centers[basis.inliers]
    beta = basis.coefficients
    spline = ThinPlateSpline(centers, beta, weights=voronoi_areas(centers, (h, w)),
                             smoothing=smoothing, scale=0.5 * float(np.hypot(h, w)))
    gy, gx = coarse_grid((h, w), grid_step)
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    # where the field is kept in the cone: chosen by the beads held out one at a time,
    # as for one image (the paper's reduced cone everywhere only where it predicts them
    # better)
    loo = np.asarray(spline.loo_residuals).reshape(beta.shape)
    constraint, scores = choose_constraint(beta, beta - loo, basis.basis)
    coarse, cone = keep_in_cone(np.asarray(spline(nodes), np.float64).reshape(len(nodes), -1),
                                beta, basis.basis, constraint)
    coefficients = coarse.T.reshape(basis.n_psf, len(gy), len(gx))
    meta = {
        "psf_radius": r, "z_radius": z_radius, "plane": plane, "focus_slice": focus,
        "n_psf": basis.n_psf, "n_beads_used": int(basis.inliers.sum()),
        "bead_positions": centers.round(3).tolist(),
        **focus_record(foci[basis.inliers], plane, surface, voxel_size),
        "smoothing": [float(s) for s in spline.smoothing],
        "field_constraint": {"chosen": constraint, **scores},
        "threshold": threshold, "grid_step": grid_step, "image_shape": [depth, h, w],
        "image_dtype": str(np.asarray(stack).dtype), "bead_counts": beads.counts(),
        "saturation": saturation_record(np.asarray(stack).max(axis=0), beads, r, None),
    }
    op = ProductConvolution3D(basis.basis, coefficients, shape=(depth, h, w), grid=(gy, gx),
                              plane=plane, voxel_size=voxel_size, metadata=meta)
    return gx, gy, cone, coefficients, meta, op


def _held_out(stack, smoothing, voxel_size, holdout, shape, plane, patches, basis, gx, gy,
              coefficients, meta, est):
    """The field model judged on beads held out of it against one 3D PSF, the beads' mean:
    never worse than one PSF, the estimate falls back to it where it loses."""
    depth, h, w = shape
    if holdout and meta["n_beads_used"] >= 2 * FOLDS:
        try:  # a score of the model: it never aborts the estimate
            held = yield from within(iter_heldout_error_3d(est, stack,
                                                           smoothing=smoothing), 0.9, 0.1)
            est.heldout = held
            meta["heldout"] = held.summary()
        except ValueError as exc:
            meta["heldout"] = {"n_beads": 0, "not_measured": str(exc)}
    if holdout and (meta.get("heldout") or {}).get("n_beads"):
        summary = meta["heldout"]
        yield Progress("held-out", 1.0, f"held-out beads: residual "
                       f"{summary['residual_median']:.3f} ({summary['over_floor']:.2f}x the "
                       f"noise floor), one 3D PSF {summary['single_median']:.3f}")
        if not summary["field_wins"]:  # never worse than one PSF: fall back to it
            kernel = patches.psf[basis.inliers].mean(axis=0)[None]
            meta.update(n_psf=1, field_model="shift-invariant", field_model_reason=(
                f"on {summary['n_beads']} held-out beads one 3D PSF (median residual "
                f"{summary['single_median']:.3f}) beat the field of {basis.n_psf} kernels "
                f"({summary['residual_median']:.3f}): one 3D PSF, the beads' mean"))
            est.operator = ProductConvolution3D(
                kernel, np.ones((1, 1, 1)), shape=(depth, h, w),
                grid=(np.array([(h - 1) / 2]), np.array([(w - 1) / 2])), plane=plane,
                voxel_size=voxel_size, metadata=meta)
        else:
            est.operator = ProductConvolution3D(
                basis.basis, coefficients, shape=(depth, h, w), grid=(gy, gx), plane=plane,
                voxel_size=voxel_size, metadata=meta)


def _one_psf(stack, vol, beads, patches, kept, foci, surface, plane, z_radius, r,
             threshold, grid_step, voxel_size, focus):
    """The model of too few beads for a basis (fewer than ``min_beads_for(1)``): their
    mean 3D patch, the same everywhere (a field cannot be learnt from them; said in
    ``metadata["field_model_reason"]``)."""
    depth, h, w = vol.shape
    kernel = patches.psf.mean(axis=0)[None]
    n = len(kept)
    basis = PsfBasis(kernel, np.ones((n, 1)), np.ones(n, bool), np.zeros(n), np.zeros(0),
                     float("nan"), 1)
    reason = (f"{n} usable bead(s), fewer than {min_beads_for(1)}: one 3D PSF for the whole "
              "field, their mean")
    meta = {"psf_radius": r, "z_radius": z_radius, "plane": plane, "focus_slice": focus,
            "n_psf": 1, "n_beads_used": n, "bead_positions": patches.centers.round(3).tolist(),
            **focus_record(foci, plane, surface, voxel_size),
            "field_model": "shift-invariant", "field_model_reason": reason,
            "threshold": threshold, "grid_step": grid_step, "image_shape": [depth, h, w],
            "image_dtype": str(np.asarray(stack).dtype), "bead_counts": beads.counts()}
    op = ProductConvolution3D(kernel, np.ones((1, 1, 1)), shape=(depth, h, w),
                              grid=(np.array([(h - 1) / 2]), np.array([(w - 1) / 2])),
                              plane=plane, voxel_size=voxel_size, metadata=meta)
    yield Progress("fit", 1.0, reason)
    return Estimation3D(op, beads, patches, kept, basis, reduce_cone(np.ones((n, 1))), foci,
                        surface)


estimate_operator_3d = drained(iter_estimate_operator_3d, "estimate_operator_3d",
                               result=attrgetter("operator"), returns="""\
    ProductConvolution3D
        ``psf_at(y, x)`` is a point on the bead plane at ``(y, x)`` seen on the stack's
        planes, shape (Z, P, P).
""")


__all__ = ["Estimation3D", "bead_stack", "estimate_operator_3d", "iter_estimate_operator_3d"]
