"""Estimate a product-convolution operator from one image of beads (paper, sec. 2.3).

detect -> centre -> extract patches (background, window, normalise) -> PCA with outlier
rejection -> weighted thin-plate splines of the coefficients on a coarse grid -> cone
projection -> :class:`~napari_psfspace.core.model.operator.ProductConvolution`.

The work is a generator (:func:`iter_estimate`) that yields :class:`Progress` records and
returns an :class:`Estimation`; :func:`estimate_operator` drains it and returns the
operator. A GUI runs the generator in a worker thread and can stop between steps.

**Denoising** (``denoise``, :mod:`~napari_psfspace.core.model.denoise`): the basis is
learnt from patches filtered by one Wiener filter, each bead weighted by ``1 / ||p||^2``
of its raw patch, and the basis images are then refitted to the raw patches of all beads
at once given the smooth field and shrunk by their own noise. Off: the paper's plain PCA
of l2-normalised patches.

**Point-source PSFs.** With the beads' diameter (from their data sheet: 200 nm beads at
100 nm pixels give 2.0), the learnt PSFs are corrected for the bead's projected sphere,
divided out in Fourier where the signal stands above the noise so that noise is not
amplified (:func:`~napari_psfspace.core.beads.sphere.remove_sphere`). Motion blur (a smear
common to all beads, :mod:`~napari_psfspace.core.model.motion`) is always looked for and
reported; the model keeps it, as it blurs a sample imaged in the same exposure just as
much, unless ``remove_motion`` asks for a calibration of the optics alone (the sample was
still). The held-out residual is measured with the uncorrected model: it judges the beads'
own images.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from operator import attrgetter

import numpy as np

from ..beads.centering import refine_centers
from ..beads.detect import (
    FAINT,
    OUTLIER,
    STRUCTURE,
    Beads,
    NoBeadsError,
    detect_beads,
    flag_unusable,
)
from ..beads.overlap import neighbour_light
from ..beads.patches import Patches, extract_patches
from ..beads.saturation import saturation_record
from ..beads.sphere import remove_sphere
from ..beads.spikes import find_spikes
from ..beads.window import bump_window, radial_distance
from ..common.progress import Progress
from ..common.spacing import bead_border, centring_sigma
from ..common.threads import blas_threads
from ..common.twins import drained
from ..common.validate import (
    as_array,
    as_image,
    check_grid_step,
    check_n_psf,
    check_positive,
    check_psf_radius,
    check_saturation,
    check_threshold,
)
from .cone import Cone
from .deblend import crowded, deblend
from .estimate_record import basis_record, hot_pixel_record, left_out_record
from .fewbeads import FEW_BEADS, fit_few_beads
from .heldout import HeldoutResiduals, heldout_residuals, split_holdout
from .motion import detect_motion
from .motion import remove_motion as divide_motion
from .operator import ProductConvolution
from .patch_fit import fit_patches
from .pca import PsfBasis, min_beads_for

#: The float32 images of the image's size estimation holds at once (its detection's
#: filtered copies, the background, the neighbours' model), with a margin: checked first.
ESTIMATE_IMAGES = 10


@dataclass
class Estimation:
    """Everything an estimation produced, for review and diagnostics.

    Attributes
    ----------
    operator : ProductConvolution
        The model fitted on all usable beads.
    beads : Beads
        Every detection with its final status (kept, border, neighbour, saturated,
        faint, outlier).
    patches : Patches
        Patches of the beads that entered the PCA (status kept or outlier), in the
        order of ``patch_index``.
    patch_index : ndarray of shape (K,)
        Index into ``beads`` of each patch.
    basis : PsfBasis
        The PCA result (basis, coefficients, z-scores, singular values).
    cone : Cone
        Reduced cone of the observed coefficients.
    heldout : HeldoutResiduals or None
        Residuals on held-out beads of a model fitted without them.
    """

    operator: ProductConvolution
    beads: Beads
    patches: Patches
    patch_index: np.ndarray
    basis: PsfBasis
    cone: Cone
    heldout: HeldoutResiduals | None = None
    info: dict = field(default_factory=dict)


@blas_threads
def iter_estimate(
    image,
    *,
    psf_radius: float,
    n_psf: int | str | None = None,
    smoothing: float | None = None,
    threshold: float = 8.0,
    beads: Beads | None = None,
    holdout: float | None = 0.2,
    grid_step: float = 32.0,
    saturation: float | None = None,
    z_threshold: float = 3.0,
    patch_filter: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    bead_diameter: float = 0.0,
    denoise: bool = True,
    remove_motion: bool = False,
    motion_test: bool = True,
) -> Generator[Progress, None, Estimation]:
    """Learn the space-varying PSF of a microscope from one image of beads.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Image of scattered sub-resolution beads, any real dtype (a stack is refused).
    psf_radius : float
        Upper bound ``r`` of the PSF radius in pixels (beyond it the PSF is lost in the
        noise); beads closer than ``2 r`` to each other are not used.
    n_psf : int, "heldout", "rule" or None
        Size ``I`` of the PSF basis. Default (None, "heldout"): the lowest
        leave-one-bead-out error of the whole model; "rule": the Gavish-Donoho threshold.
    smoothing : float, optional
        Thin-plate smoothing ``eta`` (coordinates scaled to the image's half-diagonal);
        default: chosen per coefficient by leave-one-bead-out cross-validation.
    threshold : float
        Detection threshold in noise standard deviations of the filtered image.
    beads : Beads, optional
        A bead table (e.g. edited by hand) whose ``kept`` beads are used, not detected.
    holdout : float or None
        Fraction of the beads held out to measure the model's residual
        (``metadata['heldout']``; the model is then refitted on all beads). None/0: none.
    grid_step : float
        Spacing (pixels) of the grid on which the coefficient maps are stored.
    saturation : float, optional
        Pixel value at which the detector saturates (default: the dtype maximum for
        integer images); beads touching it are not used.
    z_threshold : float
        The outlier test's threshold, robust standard deviations (:func:`~.pca.learn_basis`).
    patch_filter : callable, optional
        ``patch_filter(psf, centers) -> psf`` on the normalised patches (K, P, P) before
        the PCA (e.g. :class:`~napari_psfspace.core.diagnosis.effects.bead_size.SizeFilter`).
    bead_diameter : float
        The beads' diameter in pixels, divided out of the learnt PSFs (module docstring;
        ``metadata["bead_correction"]``). 0: point sources.
    denoise : bool
        Use the beads by their information (module docstring; ``metadata["denoise"]``).
        False: the paper's plain PCA of l2-normalised patches.
    remove_motion : bool
        Divide a motion smear found out of the PSFs, for a calibration of the optics
        alone (module docstring); it is reported either way (``metadata["motion"]``).
    motion_test : bool
        False: no motion-blur test (``metadata["motion"]`` None), for a cross-fit's folds.

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    Estimation
        The operator (``H u = sum_i h_i * (alpha_i u)``; ``psf_at(y, x)`` gives the PSF
        anywhere) with the beads, patches, basis, cone and held-out residuals it was
        learnt from.

    Raises
    ------
    ValueError
        Bad input, and :class:`~napari_psfspace.core.beads.detect.NoBeadsError` (a
        ValueError) when there are too few usable beads for the basis size.
    """
    raw, img, shape, r, grid_step, saturation, z_threshold, fixed_n, bead_diameter = _checked(
            image, psf_radius, n_psf, smoothing, grid_step, saturation, z_threshold, bead_diameter)
    beads, kept, reasons, patches = yield from _patches(
            threshold, beads, saturation, patch_filter, raw, img, r)
    motion, removers, spline, heldout, few, denoised, cone, op, basis = yield from _fit(
            n_psf, smoothing, beads, holdout, grid_step, z_threshold, bead_diameter, denoise,
            remove_motion, motion_test, shape, fixed_n, kept, patches)
    meta = _metadata(n_psf, smoothing, threshold, beads, grid_step, saturation, z_threshold,
                     remove_motion, raw, shape, r, reasons, patches, motion, removers, spline,
                     heldout, few, denoised, cone, op, basis)
    op = ProductConvolution(op.basis, op.coefficients, shape=shape, grid=op.grid, metadata=meta)
    yield Progress("fit", 1.0, f"basis of {basis.n_psf} PSFs from {meta['n_beads_used']} beads"
                   + ("" if few is None or few.field_model != "shift-invariant"
                      else " (one PSF for the whole field)"))
    return Estimation(op, beads, patches, kept, basis, cone, heldout, meta)


def _checked(image, psf_radius, n_psf, smoothing, grid_step, saturation, z_threshold,
             bead_diameter):
    """The image as recorded and as float64, and the settings checked; one clear line for a
    bad value before any work."""
    raw = np.asarray(as_array(image, "image"))
    img = as_image(raw, copies=ESTIMATE_IMAGES)
    shape = img.shape
    r = check_psf_radius(psf_radius, shape)
    grid_step = check_grid_step(grid_step, np.shape(image)[-2:])
    saturation = check_saturation(saturation)
    z_threshold = check_threshold(z_threshold, "z_threshold")
    fixed_n = check_n_psf(n_psf)
    if smoothing is not None:
        check_positive(smoothing, "smoothing", allow_zero=True)
    bead_diameter = check_bead_diameter(bead_diameter, r)
    return raw, img, shape, r, grid_step, saturation, z_threshold, fixed_n, bead_diameter


def _patches(threshold, beads, saturation, patch_filter, raw, img, r):
    """The usable beads, centred, and their patches; in a crowded field, the neighbours'
    light taken out with the model's PSFs."""
    beads, img = find_usable_beads(raw, img, r, beads=beads, threshold=threshold,
                                   saturation=saturation)
    yield Progress("detect", 0.15, beads.summary())
    kept = centre_beads(img, beads, r)
    yield Progress("centre", 0.3, f"{len(kept)} beads centred to sub-pixel precision")
    kept, patches, reasons = usable_patches(img, beads, kept, r, patch_filter=patch_filter)
    yield Progress("patches", 0.45, f"{len(kept)} patches of {patches.size} px")
    if len(kept) > FEW_BEADS and crowded(kept, beads.positions, patches.size):
        def cut(light, last):
            k, new, more = usable_patches(img, beads, last, r, patch_filter=patch_filter,
                                          neighbours=light)
            reasons.update(more)
            return k, new

        kept, patches = deblend(patches, kept, img, beads, r, cut)
        yield Progress("patches", 0.5, "neighbours' light taken out with the model's PSFs")
    return beads, kept, reasons, patches


def _fit(n_psf, smoothing, beads, holdout, grid_step, z_threshold, bead_diameter, denoise,
         remove_motion, motion_test, shape, fixed_n, kept, patches):
    """The basis, the field and the cone: from a handful of beads, the richest model they
    support; else fitted on all beads after a fit without the held-out ones measures the
    model's residual on them. Beads the outlier test rejects get that status."""
    motion = (motion_of(patches) if motion_test or remove_motion else None)
    removers = PointSource(bead_diameter, motion if remove_motion else None)
    support = radial_distance(patches.size) < patches.r_ext
    few = heldout = spline = None
    denoised: dict = {}
    if len(kept) <= FEW_BEADS:  # a handful of beads: the richest model they support
        few = fit_few_beads(patches, shape, n_psf=fixed_n, support=support,
                            grid_step=grid_step, basis_filter=removers(patches.psf))
        heldout, op, cone = few.heldout, few.operator, few.cone
        n = len(patches)
        basis = PsfBasis(few.basis, few.coefficients, np.ones(n, bool), np.zeros(n),
                         np.zeros(0), float("nan"), few.n_psf)
        yield Progress("held-out", 0.7, few.reason)
    else:
        def fit(sub: Patches, *, final: bool = False):
            return fit_patches(sub, shape, n_psf=n_psf, smoothing=smoothing,
                               grid_step=grid_step, z_threshold=z_threshold,
                               denoise=denoise, basis_filter=removers if final else None,
                               record=denoised)

        need = min_beads_for(fixed_n or 1)
        if holdout:
            held = split_holdout(patches.centers, shape, holdout)
            if np.count_nonzero(~held) >= need and np.count_nonzero(held) >= 1:
                _, op_train, _, _ = fit(patches.subset(~held))
                heldout = heldout_residuals(op_train, patches.subset(held))
                yield Progress("held-out", 0.7,
                               f"held-out residual {heldout.summary()['residual_mean']:.3f} "
                               f"on {int(held.sum())} beads")
        basis, op, cone, spline = fit(patches, final=True)
        beads.status[kept[~basis.inliers]] = OUTLIER
    return motion, removers, spline, heldout, few, denoised, cone, op, basis


def _metadata(n_psf, smoothing, threshold, beads, grid_step, saturation, z_threshold,
              remove_motion, raw, shape, r, reasons, patches, motion, removers, spline, heldout,
              few, denoised, cone, op, basis):
    """The operator's metadata: the settings, the beads used and left out, the basis and the
    field chosen, the held-out residual and the corrections."""
    meta = {
        "psf_radius": r,
        "r_ext": patches.r_ext,
        **basis_record(basis, n_psf, spline, smoothing, few),
        "threshold": threshold,
        "z_threshold": float(z_threshold) if np.isfinite(z_threshold) else None,
        "grid_step": grid_step,
        "image_shape": list(shape),
        "image_dtype": str(raw.dtype),
        "bead_counts": beads.counts(),
        "saturation": saturation_record(raw, beads, r, saturation),
        "hot_pixels": hot_pixel_record(beads.hot_pixels),
        "n_beads_used": int(basis.inliers.sum()),
        "bead_positions": patches.centers[basis.inliers].round(3).tolist(),
        "left_out": left_out_record(beads, reasons),
        "cone_generators": int(len(cone.generators)),
        "field_constraint": op.metadata.get("field_constraint"),
        "heldout": heldout.summary() if heldout is not None else None,
        "denoise": ({"passband": denoised.get("passband"),
                     "basis_noise": denoised.get("noise_rel")} if denoised else None),
        **removers.records(motion, remove_motion),
    }
    return meta


def find_usable_beads(raw: np.ndarray, img: np.ndarray, r: float, *, beads: Beads | None,
                      threshold: float, saturation: float | None) -> tuple[Beads, np.ndarray]:
    """Step 1: the beads (detected, or the given table checked here) and the image with
    its hot pixels inpainted.

    Returns
    -------
    beads : Beads
        A new table (the given one is not modified).
    image : ndarray of shape (M, N)
    """
    if beads is None:
        beads = detect_beads(raw, r, threshold=threshold, saturation=saturation)
        return beads, beads.clean_image(img)
    beads = beads.copy()
    if beads.hot_pixels is None:  # a table made by hand: look for spikes here
        beads.hot_pixels = find_spikes(raw)
    img = beads.clean_image(img)
    if saturation is None and raw.dtype.kind in "ui":
        saturation = float(np.iinfo(raw.dtype).max)
    flag_unusable(beads, img, r, saturation=saturation, border=bead_border(r))
    return beads, img


def centre_beads(img: np.ndarray, beads: Beads, r: float) -> np.ndarray:
    """Step 2: the kept beads centred sub-pixel in place, then checked again (a bead may
    have moved towards the border). Returns the indices of the beads still kept.

    Raises
    ------
    NoBeadsError
        No bead is kept.
    """
    kept = np.flatnonzero(beads.kept)
    if len(kept) == 0:
        raise NoBeadsError(
            f"No usable bead (0 kept): {beads.summary()}. Lower `threshold`, check "
            f"`psf_radius` = {r:g} px, or image a denser bead slide."
        )
    beads.positions[kept] = refine_centers(img, beads.positions[kept],
                                           sigma=centring_sigma(r), half=int(np.ceil(r)))
    flag_unusable(beads, img, r, saturation=None, border=bead_border(r))
    return np.flatnonzero(beads.kept)


def kept_patches(img: np.ndarray, beads: Beads, kept: np.ndarray, r: float, *,
                 neighbours=None) -> Patches:
    """The patches of the beads ``kept`` (indices into ``beads``), the other detections'
    modelled light taken out (``neighbours``, default
    :func:`~napari_psfspace.core.beads.overlap.neighbour_light`; background structure
    excepted): every path that learns from an image's beads (the estimate, the family's)
    cuts the same patches."""
    light = neighbours
    if light is None and SUBTRACT_NEIGHBOURS:
        light = neighbour_light(img, beads.positions[beads.status != STRUCTURE], r)
    return extract_patches(img, beads.positions[kept], r, neighbours=light)


def usable_patches(img: np.ndarray, beads: Beads, kept: np.ndarray, r: float, *,
                   patch_filter=None, neighbours=None
                   ) -> tuple[np.ndarray, Patches, dict[int, str]]:
    """Step 3: the kept beads' patches (background removed, windowed, sum 1), faint
    beads left out (status set to faint in ``beads``), ``patch_filter`` applied; the
    neighbours' light as :func:`kept_patches` takes it out.

    Returns
    -------
    kept : ndarray of shape (K,)
        Indices into ``beads`` of the patches.
    patches : Patches
    reasons : dict
        Bead index -> why it was left out, beyond its status.
    """
    patches = kept_patches(img, beads, kept, r, neighbours=neighbours)
    reasons: dict[int, str] = {}
    faint, why_faint = faint_beads(patches.flux)
    if faint.any():
        beads.status[kept[faint]] = FAINT
        reasons.update({int(i): w for i, w in zip(kept[faint], why_faint[faint], strict=True)})
        kept, patches = kept[~faint], patches.subset(~faint)
    if len(kept) == 0:
        raise NoBeadsError(f"No usable bead after background removal. {beads.summary()}.")
    if patch_filter is not None:
        psf = patch_filter(patches.psf, patches.centers)
        total = psf.sum(axis=(1, 2))
        psf = psf / np.where(total > 0, total, 1.0)[:, None, None]
        patches = Patches(patches.centers, patches.raw, patches.background, psf,
                          patches.flux, patches.noise, patches.r, patches.r_ext)
    return kept, patches, reasons


def motion_of(patches: Patches):
    """Step 4: the motion-blur test on the patches
    (:func:`~napari_psfspace.core.model.motion.detect_motion`)."""
    window = bump_window(patches.size, patches.r, patches.r_ext)
    return detect_motion(patches.psf, patches.noise / patches.flux, window,
                         positions=patches.centers)


class PointSource:
    """The basis filter that makes the learnt PSFs those of a point source: divides the
    beads' own sphere out (``bead_diameter`` > 0) and a smear found in them (``motion``,
    when it is to be removed and was detected). Called with the patches' PSFs, it gives
    the filter (None when there is nothing to remove); it records what it did."""

    def __init__(self, bead_diameter: float, motion=None):
        self.bead_diameter = bead_diameter
        self.motion = motion if motion is not None and motion.detected else None
        self.sphere: dict = {}
        self.removed: dict = {}

    def __call__(self, psf: np.ndarray):
        steps = []
        if self.bead_diameter:
            steps.append(_basis_remover(
                psf, lambda h, **kw: remove_sphere(h, self.bead_diameter, **kw), self.sphere))
        if self.motion is not None:
            m = self.motion
            steps.append(_basis_remover(
                psf, lambda h, **kw: divide_motion(h, m.length_px, m.angle_deg, **kw),
                self.removed))
        if not steps:
            return None

        def chain(h):
            for step in steps:
                h = step(h)
            return h
        return chain

    def records(self, motion, remove_motion: bool) -> dict:
        """The metadata of what was tested and removed: ``motion``, ``bead_diameter_px``
        and ``bead_correction``."""
        record = None if motion is None else motion.to_dict()
        if remove_motion and record is not None and not motion.detected:
            record["removed"] = None
            record["note"] = ("remove_motion was asked, but no motion blur was found: "
                              "nothing removed")
        if record is not None and self.removed:
            record = {**record, "removed": self.removed}
        return {
            "motion": record,
            "bead_diameter_px": self.bead_diameter,
            "bead_correction": ({**self.sphere, "note": "the PSFs are those of a point "
                                 "source: the beads' projected sphere was divided out; the "
                                 "held-out residual judges bead images with the uncorrected "
                                 "model"} if self.bead_diameter else None),
        }


#: A detection whose flux is below this fraction of the median kept bead's carries too
#: little of the PSF to shape it (a noise spot, a speck of dust): it is left out as faint.
#: A bead two and a half sd below the median of a log-normal brightness spread of sd 1 (the
#: widest of the scene set) still has 8 % of it.
FAINT_RATIO = 0.05
#: Take the other detections' modelled light out of each patch.
SUBTRACT_NEIGHBOURS = True


def faint_beads(flux: np.ndarray, ratio: float = FAINT_RATIO) -> tuple[np.ndarray, np.ndarray]:
    """Which beads are too faint to shape the PSF, and why, shapes (K,) and (K,) str.

    A bead's patch flux (background removed) at or below zero holds no signal; one below
    ``ratio`` times the median flux of the beads with signal is noise or dust beside
    them: its normalised patch is mostly noise, and in a few-bead model it would weigh as
    much as a real bead.
    """
    flux = np.asarray(flux, np.float64)
    why = np.full(len(flux), "", dtype=object)
    none = ~(flux > 0)
    why[none] = "no signal above its background (flux <= 0)"
    faint = none.copy()
    if (~none).any():
        median = float(np.median(flux[~none]))
        low = ~none & (flux < ratio * median)
        for i in np.flatnonzero(low):
            why[i] = (f"flux {100 * flux[i] / median:.2g} % of the median bead's, below "
                      f"{100 * ratio:g} %: too faint to shape the PSF")
        faint |= low
    return faint, why.astype(str)


def _basis_remover(psf: np.ndarray, remove: Callable, record: dict):
    """A basis filter ``h -> remove(h, reference=..., noise=...)[0]`` for PSFs learnt
    from ``psf`` (K, P, P) sum-1 patches: their mean sets the signal-to-noise ratio, the
    difference of two halves' means its noise (the re-sampling colours it). ``record``
    receives the remover's info (:func:`~napari_psfspace.core.beads.sphere.remove_sphere`,
    :func:`~napari_psfspace.core.model.motion.remove_motion`)."""
    noise = None
    if len(psf) >= 2:
        # var(A - B) = s^2 K / (n_a n_b); the mean of all K has s^2 / K
        noise = psf[0::2].mean(axis=0) - psf[1::2].mean(axis=0)
        noise *= np.sqrt(len(psf[0::2]) * len(psf[1::2])) / len(psf)
    reference = psf.mean(axis=0)

    def apply(h):
        out, info = remove(h, reference=reference, noise=noise)
        record.update(info)
        return out

    return apply


def check_bead_diameter(bead_diameter, psf_radius: float) -> float:
    """Check ``bead_diameter`` (pixels): 0 (point sources) up to the PSF radius."""
    d = check_positive(bead_diameter if bead_diameter is not None else 0.0, "bead_diameter",
                       allow_zero=True)
    if d > psf_radius:
        raise ValueError(
            f"`bead_diameter` = {d:g} px is larger than `psf_radius` = {psf_radius:g} px: a "
            "bead that large is not a point source for these optics. Check the units (the "
            "API takes pixels; the command line and the widgets take nanometres).")
    return d


estimate_operator = drained(iter_estimate, "estimate_operator", result=attrgetter("operator"),
                              returns="""\
    ProductConvolution
        ``H u = sum_i h_i * (alpha_i u)``; ``psf_at(y, x)`` gives the PSF anywhere.
""")


__all__ = ["Estimation", "estimate_operator", "iter_estimate"]
