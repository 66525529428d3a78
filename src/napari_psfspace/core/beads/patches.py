"""Extraction of centred, background-free, windowed and normalised PSF patches.

Paper, Appendix A and B, section 2.5: each bead is re-sampled (quintic spline) so that
its sub-pixel centre falls on the patch centre, its background is removed (a plane fitted
on a ring beyond the window: :func:`~napari_psfspace.core.beads.background.ring_background`),
a bump window confines it to radius ``r_ext = 1.2 r``, and it is normalised to sum 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from ..common.progress import check_halt
from ..common.validate import as_image, check_psf_radius
from .background import fit_background, ring_background
from .centering import gather_windows
from .window import bump_window, radial_distance

#: Outer radius of the window relative to the PSF radius (paper: r_ext = 1.2 r).
R_EXT_FACTOR = 1.2
#: Order of the spline that re-samples a patch onto its bead's sub-pixel centre. A spline
#: of order ``n`` attenuates a frequency ``w`` (radians a pixel) by about ``(w / pi) **
#: (n + 1)``: a PSF sampled near Nyquist is visibly smoothed by a cubic, on each bead by
#: its own sub-pixel offset (none at a whole pixel, most at half of one). The quintic
#: has far less of that bias, and smooths the noise a little less: noise-free and
#: quantised fields read better with it, fields of plain shot noise slightly worse
#: (``bench_estimator_ladder.py``, ``bench_gradient.py``; ``tests/test_subpixel.py``).
SPLINE_ORDER = 5
#: Pixels beyond a patch its spline is prefiltered on: the prefilter's reach from the
#: window's edge (its pole, 0.43 for the quintic, to this power) is then under 1 %.
SPLINE_MARGIN = 6


def patch_size(psf_radius: float, r_ext_factor: float = R_EXT_FACTOR) -> int:
    """Odd patch size ``2 ceil(r_ext) + 1`` for a PSF radius in pixels."""
    return 2 * int(np.ceil(r_ext_factor * psf_radius)) + 1


@dataclass
class Patches:
    """PSF patches of a set of beads.

    Attributes
    ----------
    centers : ndarray of shape (K, 2)
        Sub-pixel bead centres (row, column) in pixels in the image.
    raw : ndarray of shape (K, P, P)
        Image re-sampled around each centre (centre at pixel ``P // 2``), image units.
    background : ndarray of shape (K, P, P)
        Fitted polynomial background of each patch, image units.
    psf : ndarray of shape (K, P, P)
        ``(raw - background) * window``, normalised to sum 1.
    flux : ndarray of shape (K,)
        Sum of ``(raw - background) * window`` before normalisation: the bead's
        integrated intensity in image units.
    noise : ndarray of shape (K,)
        Robust standard deviation of ``raw - background`` outside radius ``r``.
    r, r_ext : float
        PSF radius and window radius in pixels.
    """

    centers: np.ndarray
    raw: np.ndarray
    background: np.ndarray
    psf: np.ndarray
    flux: np.ndarray
    noise: np.ndarray
    r: float
    r_ext: float

    def __len__(self) -> int:
        return len(self.centers)

    @property
    def size(self) -> int:
        """Patch size P (odd)."""
        return self.raw.shape[-1]

    @property
    def peak_snr(self) -> np.ndarray:
        """Peak of the background-free patch over the noise, shape (K,)."""
        peak = (self.raw - self.background).reshape(len(self), -1).max(axis=1)
        return peak / np.maximum(self.noise, 1e-12)

    def subset(self, index) -> Patches:
        """The patches selected by an index array or boolean mask."""
        return Patches(self.centers[index], self.raw[index], self.background[index],
                       self.psf[index], self.flux[index], self.noise[index], self.r,
                       self.r_ext)


def resample_patches(image: np.ndarray, centers: np.ndarray, size: int) -> np.ndarray:
    """Spline re-sampling (:data:`SPLINE_ORDER`) of ``(size, size)`` patches centred on
    sub-pixel centres.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    centers : ndarray of shape (K, 2)
        Centres (row, column) in pixels.
    size : int
        Odd patch size.

    Returns
    -------
    ndarray of shape (K, size, size), float64
    """
    half = size // 2
    margin = SPLINE_MARGIN
    wins = gather_windows(image, centers, half + margin).astype(np.float64)
    frac = centers - np.round(centers)
    g = np.arange(size, dtype=np.float64) + margin
    out = np.empty((len(centers), size, size))
    for k in range(len(centers)):
        check_halt()
        yy = (g + frac[k, 0])[:, None] * np.ones((1, size))
        xx = np.ones((size, 1)) * (g + frac[k, 1])[None, :]
        out[k] = ndi.map_coordinates(wins[k], [yy, xx], order=SPLINE_ORDER,
                                        mode="nearest")
    return out


def observed_mask(centers: np.ndarray, size: int, shape: tuple[int, int]) -> np.ndarray:
    """Which pixels of each re-sampled patch lie in the image, shape (K, size, size), bool.

    Pixel ``(i, j)`` of patch ``k`` samples the image at ``centers[k] + (i, j) - size // 2``;
    it is observed when that point lies on an image pixel (rows ``-0.5`` to ``M - 0.5``).
    """
    c = np.asarray(centers, np.float64).reshape(-1, 2)
    off = np.arange(size) - size // 2
    rows = c[:, 0, None] + off[None, :]
    cols = c[:, 1, None] + off[None, :]
    h, w = shape
    in_r = (rows >= -0.5) & (rows < h - 0.5)
    in_c = (cols >= -0.5) & (cols < w - 0.5)
    return in_r[:, :, None] & in_c[:, None, :]


def extract_patches(
    image,
    centers,
    psf_radius: float,
    *,
    r_ext_factor: float = R_EXT_FACTOR,
    background: str = "ring",
    background_order: int = 2,
    neighbours=None,
) -> Patches:
    """Centred, background-free, windowed, sum-normalised PSF patches.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Bead image, any real dtype.
    centers : array_like of shape (K, 2)
        Sub-pixel bead centres (row, column) in pixels, typically from
        :func:`~napari_psfspace.core.beads.centering.refine_centers`.
    psf_radius : float
        PSF radius ``r`` in pixels; pixels beyond ``r`` hold background only.
    r_ext_factor : float
        Window outer radius ``r_ext = r_ext_factor * r`` (paper: 1.2).
    background : {"ring", "patch"}
        "ring": a plane fitted on a ring beyond the window, from ``r_ext`` to
        :data:`~napari_psfspace.core.beads.background.RING_OUTER` radii
        (:func:`~napari_psfspace.core.beads.background.ring_background`), or "patch"'s
        for a bead the ring leaves no light; "patch": the paper's polynomial of
        ``background_order`` fitted to the patch beyond ``r``, which takes part of the
        PSF's wings for background.
    background_order : int
        Order of the "patch" background polynomial (paper: 2).
    neighbours : NeighbourLight, optional
        A model of the other detections' light
        (:func:`~napari_psfspace.core.beads.overlap.neighbour_light`), taken out of each
        patch before its background is fitted: a bead kept beside a neighbour adding a
        few percent of its light (the neighbour rule) keeps little of it.

    Returns
    -------
    Patches
        Patches of size ``P = 2 ceil(r_ext) + 1``. A patch whose background-free sum
        is not positive keeps ``psf`` at zero and ``flux <= 0``; callers drop it. A bead
        whose patch reaches past the image's edge (centre at least ``r`` in: its PSF
        lies in the image) has its background fitted on the pixels in the image, and
        ``raw`` equal to it beyond the edge (no light there).
    """
    check_halt()
    img = as_image(image)
    r = check_psf_radius(psf_radius, img.shape)
    if r_ext_factor <= 1:
        raise ValueError(f"`r_ext_factor` must be > 1, got {r_ext_factor}.")
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    if background not in ("ring", "patch"):
        raise ValueError(f"`background` must be 'ring' or 'patch', got {background!r}.")
    r_ext = r_ext_factor * r
    size = patch_size(r, r_ext_factor)
    raw = resample_patches(img, centers, size)
    if neighbours is not None:
        off = np.arange(size, dtype=np.float64) - size // 2
        grid = np.stack(np.meshgrid(off, off, indexing="ij"), -1).reshape(-1, 2)
        for k, c in enumerate(centers):
            check_halt()
            raw[k] -= neighbours.around(c, c + grid).reshape(size, size)
    seen = observed_mask(centers, size, img.shape)
    partial = not seen.all()
    window = bump_window(size, r, r_ext)
    if background == "ring":
        bg = ring_background(img, centers, r, r_ext, size, neighbours=neighbours)
        # a ring lying on structure brighter than the bead's own surround leaves the
        # bead no light: such a bead takes its patch's own background, the paper's
        dark = np.flatnonzero(((raw - bg) * window).sum(axis=(1, 2)) <= 0)
        if len(dark):
            bg[dark] = fit_background(raw[dark], r, order=background_order,
                                      observed=seen[dark] if partial else None)
    else:
        bg = fit_background(raw, r, order=background_order, observed=seen if partial else None)
    if partial:  # beyond the edge: no light measured, the background's level
        raw = np.where(seen, raw, bg)
    signal = raw - bg
    outside = radial_distance(size) > r
    resid = signal[:, outside]
    noise = 1.4826 * np.median(np.abs(resid - np.median(resid, axis=1, keepdims=True)), axis=1)
    for k in np.flatnonzero(~seen[:, outside].all(axis=1)) if partial else ():
        resid = signal[k][outside & seen[k]]  # the pixels in the image only
        noise[k] = (1.4826 * np.median(np.abs(resid - np.median(resid))) if len(resid)
                    else 0.0)
    windowed = signal * window
    flux = windowed.sum(axis=(1, 2))
    psf = np.zeros_like(windowed)
    good = flux > 0
    psf[good] = windowed[good] / flux[good, None, None]
    return Patches(centers, raw, bg, psf, flux, noise, r, r_ext)
