"""Background structure at the scale of a bead patch (autofluorescence, debris).

Blobs of background a few tenths of the PSF radius wide spoil the model twice: the
detector takes many of them for beads (they then train the PSF model and make real
beads "neighbours"), and under the beads the per-patch polynomial cannot describe them.
The effect

1. finds the detections that are structure: each detection is compared with the PSF of
   the beads around it, blurred by Gaussians of growing width; a detection that a blur of
   at least :data:`BROAD` ``psf_radius`` describes significantly better than the PSF
   itself is wider than any bead (status ``"structure"``, which spoils no neighbour);
2. estimates a structure map from the pixels outside every bead's fit disk
   (:func:`structure_map`: normalised Gaussian smoothing at a quarter of the PSF radius,
   which also fills the disks from their surroundings, minus the smooth background) and
   subtracts it from the image;
3. re-examines the neighbours and re-centres the kept beads on the corrected image.

The held-out comparison stays honest: no pixel of a bead's fit disk enters the map that
corrects it.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from ...beads.centering import gather_windows, refine_centers
from ...beads.detect import BORDER, FAINT, KEPT, NEIGHBOUR, OUTLIER, STRUCTURE, Beads, flag_unusable
from ...beads.noise import NoiseModel
from ...beads.window import radial_distance
from ...common.progress import check_halt
from ...common.spacing import bead_border, centring_sigma
from ..residuals import fourier_shift
from .base import Context, Effect

#: Widths (units of the PSF radius) of the Gaussians by which the local PSF is blurred
#: to describe a detection.
BLUR_GRID = (0.0, 0.1, 0.2, 0.3, 0.45)
#: A detection best described by a blur of at least this width is structure (measured:
#: beads need at most 0.1, also far from their reference beads under strong aberrations).
BROAD = 0.2
#: Statuses a detection found to be structure loses (not "saturated": a clipped core
#: looks wide; not a user's "rejected", nor "companion").
RECLASSIFIED = (KEPT, NEIGHBOUR, BORDER, FAINT, OUTLIER)
#: Width of the smoothing of the structure map and radius of the bead disks left out of
#: it, units of the PSF radius.
MAP_SCALE = 0.25
MASK_RADIUS = 1.0
#: Fewest kept beads the reclassification may leave (else only the map is subtracted).
MIN_KEPT = 10


def blur_of_detections(image: np.ndarray, positions, psf_radius: float, noise: NoiseModel,
                       reference) -> tuple[np.ndarray, np.ndarray]:
    """How much wider than the PSF of the beads around it each detection is.

    Each detection's pixels within ``psf_radius`` (its level removed: the median of the
    ring ``r < rho <= 1.2 r``) are fitted by least squares, weighted by the noise model,
    with an amplitude times a shape plus a constant. The shape is the median of the
    normalised shapes of the 5 nearest ``reference`` detections (each centred by a
    Fourier shift, the median moved to the detection's sub-pixel position), blurred by a
    Gaussian of each width of :data:`BLUR_GRID`.

    Parameters
    ----------
    image : ndarray of shape (M, N)
        Image, ADU.
    positions : array_like of shape (K, 2)
        Sub-pixel detection centres (row, column), pixels.
    psf_radius : float
        PSF radius ``r``, pixels.
    noise : NoiseModel
    reference : array_like of int
        Indices of the detections taken as beads.

    Returns
    -------
    blur : ndarray of shape (K,)
        The best width, units of ``psf_radius``.
    dchi2 : ndarray of shape (K,)
        Chi-square drop from the unblurred shape to the best one.
    """
    img = np.asarray(image, dtype=np.float64)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    reference = np.asarray(reference, dtype=int).reshape(-1)
    k = len(pos)
    if k == 0 or len(reference) == 0:
        return np.zeros(k), np.zeros(k)
    r = float(psf_radius)
    half = int(np.ceil(1.2 * r))
    dist = radial_distance(2 * half + 1)
    inner = dist <= r
    win = gather_windows(img, pos, half)
    data = win - np.median(win[:, dist > r], axis=1)[:, None, None]
    frac = pos - np.round(pos)
    centred = fourier_shift(data[reference], -frac[reference]) * (dist <= 1.2 * r)
    total = centred[:, inner].sum(axis=1)
    shapes = centred / np.where(total > 0, total, 1.0)[:, None, None]
    _, near = cKDTree(pos[reference]).query(pos, k=min(5, len(reference)))
    near = np.asarray(near).reshape(k, -1)
    ones = np.ones(int(inner.sum()))
    chi2 = np.empty((k, len(BLUR_GRID)))
    for i in range(k):
        ref = fourier_shift(np.median(shapes[near[i]], axis=0)[None], frac[i][None])[0]
        var = noise.variance(win[i][inner])
        w = 1.0 / np.sqrt(var)
        d = data[i][inner]
        for j, s in enumerate(BLUR_GRID):
            m = ndi.gaussian_filter(ref, s * r) if s > 0 else ref
            design = np.stack([m[inner], ones], axis=1)
            coef, *_ = np.linalg.lstsq(design * w[:, None], d * w, rcond=None)
            chi2[i, j] = float(np.sum((d - design @ coef) ** 2 / var))
    best = np.argmin(chi2, axis=1)
    return np.asarray(BLUR_GRID)[best], chi2[:, 0] - chi2.min(axis=1)


def structure_detections(image: np.ndarray, beads: Beads, psf_radius: float,
                         noise: NoiseModel, *, min_dchi2: float = 9.0,
                         n_reference: int = 10) -> np.ndarray:
    """Detections that are background structure, not beads, shape (K,) bool.

    A detection is structure when the PSF of the beads around it blurred by at least
    :data:`BROAD` ``psf_radius`` describes it better than the PSF itself by a chi-square
    drop above ``min_dchi2`` (:func:`blur_of_detections`). Two passes: the references
    are first the ``n_reference`` strongest detections, then the (up to 50) strongest
    that the first pass found as sharp as the PSF.
    """
    pos, strength = beads.positions, beads.response
    ref = np.argsort(-strength)[:n_reference]
    blur, dchi2 = blur_of_detections(image, pos, psf_radius, noise, ref)
    sharp = np.flatnonzero(blur == 0)
    if len(sharp) >= 3:
        ref = sharp[np.argsort(-strength[sharp])][:50]
        blur, dchi2 = blur_of_detections(image, pos, psf_radius, noise, ref)
    return (blur >= BROAD) & (dchi2 > min_dchi2)


def _normalised_smoothing(image: np.ndarray, free: np.ndarray, sigma: float) -> np.ndarray:
    num = ndi.gaussian_filter(np.where(free, image, 0.0), sigma, mode="nearest")
    den = ndi.gaussian_filter(free.astype(np.float64), sigma, mode="nearest")
    return num / np.maximum(den, 1e-12)


def structure_map(image: np.ndarray, bead_positions, psf_radius: float, *,
                  pixel_mask: np.ndarray | None = None, mask_radius: float = MASK_RADIUS,
                  scale: float = MAP_SCALE) -> np.ndarray:
    """Background structure of an image, ADU, shape (M, N).

    The pixels farther than ``mask_radius * psf_radius`` from every bead (and not in
    ``pixel_mask``) are smoothed by a normalised Gaussian of width
    ``scale * psf_radius`` (at least 1 pixel), which also fills the bead disks from
    their surroundings; the smooth background (the same smoothing at width
    ``max(8, 2 psf_radius)``, which the per-patch polynomials describe) is removed.

    Parameters
    ----------
    image : ndarray of shape (M, N)
        Image, ADU.
    bead_positions : array_like of shape (K, 2)
        Centres (row, column) of the beads, pixels (not of the structure detections).
    psf_radius : float
        PSF radius, pixels.
    pixel_mask : ndarray of shape (M, N), bool, optional
        Pixels to ignore (outliers, saturated pixels).
    mask_radius, scale : float
        Units of ``psf_radius``.

    Returns
    -------
    ndarray of shape (M, N), float64
    """
    check_halt()
    img = np.asarray(image, dtype=np.float64)
    r = float(psf_radius)
    pos = np.asarray(bead_positions, dtype=np.float64).reshape(-1, 2)
    free = np.ones(img.shape, bool)
    if len(pos):
        seeds = np.zeros(img.shape, bool)
        iy = np.clip(np.round(pos[:, 0]).astype(int), 0, img.shape[0] - 1)
        ix = np.clip(np.round(pos[:, 1]).astype(int), 0, img.shape[1] - 1)
        seeds[iy, ix] = True
        free = ndi.distance_transform_edt(~seeds) > mask_radius * r
    if pixel_mask is not None:
        free &= ~np.asarray(pixel_mask, bool)
    fine = _normalised_smoothing(img, free, max(1.0, scale * r))
    return fine - _normalised_smoothing(img, free, max(8.0, 2.0 * r))


class BackgroundStructure(Effect):
    """Background structure at the scale of a bead: structure detections dropped (status
    "structure"), a structure map subtracted from the image, neighbours re-examined."""

    name = "background_structure"
    description = ("background structure at the scale of a bead (detections wider than "
                   "the PSF dropped, structure map subtracted from the image)")
    # the blobs are mostly detected as beads and masked out of the bead-free windows the
    # ``background_structure`` test reads: their secondary peaks in the beads' residuals
    # show them too (a 30-photon blob field: windows' z 0.4-4, secondary peaks 11-47)
    tests = ("background_structure", "secondary_peaks")

    def fit(self, ctx: Context, analysis) -> dict:
        r = ctx.psf_radius
        status = ctx.beads.status
        broad = structure_detections(ctx.image, ctx.beads, r, ctx.noise)
        broad &= np.isin(status, RECLASSIFIED)
        if np.count_nonzero((status == KEPT) & ~broad) < MIN_KEPT:
            broad[:] = False
        smap = structure_map(ctx.image, ctx.beads.positions[~broad], r,
                             pixel_mask=ctx.pixel_mask)
        return {"structure_detections": np.flatnonzero(broad).tolist(),
                "count": int(broad.sum()), "scale_px": float(max(1.0, MAP_SCALE * r)),
                "mask_radius_px": float(MASK_RADIUS * r), "rms_adu": float(np.std(smap))}

    def apply(self, ctx: Context, params: dict) -> Context:
        r = ctx.psf_radius
        beads = ctx.beads
        broad = np.zeros(len(beads), bool)
        broad[np.asarray(params["structure_detections"], dtype=int)] = True
        image = ctx.image - structure_map(ctx.image, beads.positions[~broad], r,
                                          pixel_mask=ctx.pixel_mask,
                                          mask_radius=params["mask_radius_px"] / r,
                                          scale=params["scale_px"] / r)
        # structure is no bead and spoils no neighbour: re-examine the neighbours
        status = beads.status.copy()
        status[broad] = STRUCTURE
        status[status == NEIGHBOUR] = KEPT
        new = beads.copy(status)
        kept = new.kept
        new.positions[kept] = refine_centers(image, new.positions[kept], sigma=centring_sigma(r),
                                             half=int(np.ceil(r)))
        flag_unusable(new, image, r, saturation=None, border=bead_border(r))
        return ctx.with_effect(self.name, params, image=image, beads=new,
                               noise=ctx.renoised(image))
