"""Rough bead detection and rejection of beads that cannot give a clean PSF patch.

Paper, Appendix A: beads are the maxima of the Laplacian of a smoothed image above a
threshold; beads closer than ``r`` to the border or ``2 r`` to another bead are
rejected, so every kept patch holds one isolated PSF. Here a neighbour is judged by the
light it adds to the patch (:mod:`~napari_psfspace.core.beads.overlap`), not by a fixed
distance.

The noise level of the filtered image is its robust (MAD) spread, never below what the
rounding of an integer image gives (variance 1/12 ADU^2 per pixel): on a nearly constant
integer background the MAD collapses towards zero and every one-count bump would otherwise
stand many "noise sd" out. At low counts (integer values, background noise below
:data:`~napari_psfspace.core.beads.scale.LOW_COUNT_SD` ADU) the filter runs on the
variance-stabilised image (:func:`~napari_psfspace.core.beads.scale.detection_image`):
there the noise is skewed and its filtered tail far heavier than its spread says.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..common import spacing
from ..common.errors import NoBeadsError
from ..common.validate import as_array, as_image, check_positive, check_psf_radius, check_saturation
from .log import local_peaks, log_response
from .maxima import (
    background_excess,
    merge_one_psf,
    merge_secondary_maxima,
    peak_amplitude,
    wider_scales,
)
from .overlap import NEIGHBOUR_SHARE, patch_shares
from .saturation import saturated_cores
from .scale import detection_image, prepare
from .spikes import (
    inpaint_pixels,
    is_integer_valued,
    pixel_noise_sd,
)

#: The float32 images of the image's size detection holds at once (the image, its
#: filtered copies and masks), counted with a margin: its memory is checked first.
DETECT_IMAGES = 8

#: Status codes of a bead, in the order in which they are assigned.
KEPT = "kept"
SATURATED = "saturated"
BORDER = "border"
NEIGHBOUR = "neighbour"
FAINT = "faint"
OUTLIER = "outlier"
REJECTED = "rejected"  # by the user (napari widgets)
HELDOUT = "heldout"  # held out of a fit, still counted as a neighbour
COMPANION = "companion"  # has a companion in its patch: judged (fitted jointly), not learnt
STRUCTURE = "structure"  # background structure, not a bead: spoils no neighbour
OFF_FOCUS = "off-focus"  # in a z-stack: its focus far off the field's focal surface
STATUSES = (KEPT, SATURATED, BORDER, NEIGHBOUR, FAINT, OUTLIER, REJECTED, HELDOUT, COMPANION,
            STRUCTURE, OFF_FOCUS)
#: Human-readable meaning of each status (shown in the widgets and the QC report).
STATUS_MEANING = {
    KEPT: "kept",
    SATURATED: "saturated",
    BORDER: "too close to the border",
    NEIGHBOUR: "too close to a neighbour",
    FAINT: "no signal above the background",
    OUTLIER: "shape unlike its neighbours' prediction",
    REJECTED: "rejected by hand",
    HELDOUT: "held out of the fit",
    COMPANION: "companion in the patch (fitted jointly, not learnt)",
    STRUCTURE: "background structure, not a bead (wider than the PSF)",
    OFF_FOCUS: "focus far off the field's focal surface, or not inside the stack",
}


#: A detection fainter than this fraction of a bead's peak amplitude does not spoil it as a
#: neighbour (see :func:`flag_unusable`).
NEIGHBOUR_RATIO = 0.05
@dataclass
class Beads:
    """Detected beads and why each was kept or rejected.

    Attributes
    ----------
    positions : ndarray of shape (M, 2), float64
        Bead centres (row, column) in pixels; integer peaks after detection,
        sub-pixel after :func:`~napari_psfspace.core.beads.centering.refine_centers`.
    response : ndarray of shape (M,)
        Detection strength: the scale-normalised negative Laplacian of Gaussian at the
        peak, in units of its robust noise standard deviation.
    status : ndarray of shape (M,), str
        One of :data:`STATUSES` for each bead.
    amplitude : ndarray of shape (M,)
        Peak value above the local background (median of the window edge), image
        units; NaN where unknown (e.g. beads added by hand).
    hot_pixels : ndarray of shape (S, 2), int64, or None
        ``(row, column)`` of the pixels found narrower than the optics can form (hot
        pixels, cosmic rays; :mod:`~napari_psfspace.core.beads.spikes`): inpainted before
        detection and masked downstream. None: not searched (e.g. a table made by hand).
    """

    positions: np.ndarray
    response: np.ndarray
    status: np.ndarray = field(default=None)
    amplitude: np.ndarray = field(default=None)
    hot_pixels: np.ndarray | None = None

    def __post_init__(self):
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 2)
        self.response = np.asarray(self.response, dtype=np.float64).reshape(-1)
        if self.status is None:
            self.status = np.full(len(self.positions), KEPT, dtype="<U10")
        self.status = np.asarray(self.status, dtype="<U10")
        if self.amplitude is None:
            self.amplitude = np.full(len(self.positions), np.nan)
        self.amplitude = np.asarray(self.amplitude, dtype=np.float64).reshape(-1)
        if self.hot_pixels is not None:
            self.hot_pixels = np.asarray(self.hot_pixels, dtype=np.int64).reshape(-1, 2)
        n = {len(self.positions), len(self.response), len(self.status), len(self.amplitude)}
        if len(n) != 1:
            raise ValueError(
                "`positions`, `response`, `status` and `amplitude` must have the same length, "
                f"got {len(self.positions)}, {len(self.response)}, {len(self.status)} and "
                f"{len(self.amplitude)}."
            )

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def kept(self) -> np.ndarray:
        """Boolean mask of the beads kept for estimation, shape (M,)."""
        return self.status == KEPT

    def counts(self) -> dict[str, int]:
        """Number of beads per status."""
        return {s: int(np.count_nonzero(self.status == s)) for s in STATUSES}

    def summary(self) -> str:
        c = self.counts()
        parts = [f"{v} {k}" for k, v in c.items() if v]
        out = f"{len(self)} beads detected: " + ", ".join(parts)
        if self.hot_pixels is not None and len(self.hot_pixels):
            out += (f"; {len(self.hot_pixels)} hot pixel(s) masked (narrower than the "
                    "optics can form)")
        return out

    def copy(self, status: np.ndarray | None = None) -> Beads:
        """A deep copy, optionally with another status array."""
        return Beads(self.positions.copy(), self.response.copy(),
                     self.status.copy() if status is None else status,
                     self.amplitude.copy(),
                     None if self.hot_pixels is None else self.hot_pixels.copy())

    def clean_image(self, image: np.ndarray) -> np.ndarray:
        """``image`` (floating) with the hot pixels inpainted (a copy when there are any)."""
        if self.hot_pixels is None or len(self.hot_pixels) == 0:
            return image
        return inpaint_pixels(image, self.hot_pixels)


def detect_beads(
    image,
    psf_radius: float,
    *,
    threshold: float = 8.0,
    sigma: float | None = None,
    saturation: float | None = None,
    border: float | None = None,
    min_separation: float | None = None,
    neighbour_ratio: float = NEIGHBOUR_RATIO,
    neighbour_share: float | None = NEIGHBOUR_SHARE,
    hot_pixels: bool = True,
) -> Beads:
    """Find beads and flag those that cannot give a clean, isolated PSF patch.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Bead image, any real dtype.
    psf_radius : float
        Upper bound ``r`` of the PSF radius in pixels (the radius beyond which the PSF
        is lost in the noise).
    threshold : float, optional
        Detection threshold in robust noise standard deviations of the filtered image
        (see :func:`log_response`). Lower finds fainter beads.
    sigma : float, optional
        Scale of the Laplacian of Gaussian in pixels. Default: ``max(1, r / 4)``, or the
        scale of the spots the image shows when it is at least :data:`RESCALE_FACTOR`
        times larger (:func:`~napari_psfspace.core.beads.scale.characteristic_scale`: a
        ring out of focus is found once, at its centre, not as several spots on its
        edge).
    saturation : float, optional
        Pixel value at or above which the detector is saturated. Default: the maximum
        of the dtype for integer images, none for floating images.
    border : float, optional
        Beads whose centre lies closer than this to the border are rejected. Default
        ``ceil(1.2 r) + 2``: the PSF patch (radius ``1.2 r``, Appendix A) must fit in
        the image with room for sub-pixel re-sampling.
    min_separation : float, optional
        A bead closer than this to another detection at least ``neighbour_ratio`` as
        bright is rejected (the paper's rule, ``2 r``). Default: none, the energy rule
        only (``neighbour_share``).
    neighbour_ratio : float
        A detection fainter than this fraction of a bead's peak does not spoil it
        (:data:`NEIGHBOUR_RATIO`; 0: every detection does).
    neighbour_share : float or None
        A bead whose neighbours add at least this share of the energy in its patch is
        rejected (:data:`~napari_psfspace.core.beads.overlap.NEIGHBOUR_SHARE`; None: the
        fixed ``min_separation`` only).
    hot_pixels : bool
        Find pixels narrower than the optics can form (hot pixels, cosmic rays,
        :func:`~napari_psfspace.core.beads.spikes.find_spikes`), inpaint them before
        detection and record them in ``Beads.hot_pixels`` for the later steps to mask.

    Returns
    -------
    Beads
        All detections with their status (kept, saturated, border, neighbour).

    Raises
    ------
    NoBeadsError
        When nothing stands above the threshold; the message gives the strongest
        response found so that the user knows how far to lower ``threshold``.
    """
    raw = np.asarray(as_array(image, "image"))
    img = as_image(raw, dtype=np.float32, copies=DETECT_IMAGES)
    r, threshold, neighbour_ratio, auto_sigma, sigma, border, saturation = _checked(
            psf_radius, threshold, sigma, saturation, border, neighbour_ratio, raw, img)
    _check_levels(img)
    floor, det, spikes, pixel_sd, img = _detection_input(image, hot_pixels, raw, img)
    resp = log_response(det, sigma, pixel_sd_floor=floor)
    peaks = local_peaks(resp, max(1, int(round(r / 2))), threshold)
    scales = []  # the wider scales that added maxima
    if auto_sigma:
        sigma, peaks, resp, scales = wider_scales(raw, img, det, peaks, resp, sigma, r,
                                                  threshold=threshold, noise_sd=pixel_sd,
                                                  floor=floor)
    peaks, strength = _merged_maxima(img, resp, peaks, r, sigma, threshold)
    amplitude, strength, peaks = _standing_out(threshold, sigma, img, r, pixel_sd, peaks, scales,
                                               strength)
    beads = Beads(peaks.astype(np.float64), strength, amplitude=amplitude,
                  hot_pixels=spikes if hot_pixels else None)
    flag_unusable(beads, img, r, saturation=saturation, border=border,
                  min_separation=min_separation, neighbour_ratio=neighbour_ratio,
                  neighbour_share=neighbour_share)
    return beads


def _checked(psf_radius, threshold, sigma, saturation, border, neighbour_ratio, raw, img):
    """The settings checked, the defaults from the PSF radius and the dtype; one clear line
    for a bad value before any work."""
    r = check_psf_radius(psf_radius, img.shape)
    threshold = check_positive(threshold, "threshold")
    neighbour_ratio = check_positive(neighbour_ratio, "neighbour_ratio", allow_zero=True)
    auto_sigma = sigma is None
    sigma = spacing.centring_sigma(r) if sigma is None else check_positive(sigma, "sigma")
    if border is None:
        border = spacing.bead_border(r)
    saturation = check_saturation(saturation)
    if saturation is None and raw.dtype.kind in "ui":
        saturation = float(np.iinfo(raw.dtype).max)
    return r, threshold, neighbour_ratio, auto_sigma, sigma, border, saturation


def _check_levels(img):
    """One clear line for an image with no beads to detect: constant, or two levels only (a
    mask)."""
    if float(img.max()) == float(img.min()):
        raise NoBeadsError(
            f"`image` is constant (every pixel equals {float(img.min()):g}): no beads to "
            "detect. Check that the right image or slice was passed."
        )
    lo, hi = float(img.min()), float(img.max())
    sub = img[::7, ::7]  # a bead image shows a third level at once; a mask never does
    if not np.any((sub != lo) & (sub != hi)) and not np.any((img != lo) & (img != hi)):
        raise NoBeadsError(
            f"`image` holds two values only ({lo:g} and {hi:g}): a mask or a thresholded "
            "image, not a bead image (a bead is a blurred spot with every level between "
            "the background and its peak). Pass the raw image."
        )


def _detection_input(image, hot_pixels, raw, img):
    """The image detection runs on (hot pixels found and inpainted, once per image in a
    ``scale.reusing`` block), its pixels' noise, the hot pixels, the image the filter runs
    on and its noise floor."""
    if hot_pixels:  # found and inpainted (once per image in a `scale.reusing` block)
        prepared = prepare(image)
        img, integer, pixel_sd, spikes = (prepared.image, prepared.integer,
                                          prepared.noise_sd, prepared.spikes)
        det, floor = prepared.detection, prepared.sd_floor
    else:
        integer = is_integer_valued(raw)
        pixel_sd = pixel_noise_sd(raw, integer=integer)
        spikes = np.zeros((0, 2), np.int64)
        det, _, floor = detection_image(img, integer=integer, noise_sd=pixel_sd)
    return floor, det, spikes, pixel_sd, img


def _merged_maxima(img, resp, peaks, r, sigma, threshold):
    """The maxima strongest first, with their strength, those of one PSF merged; one clear
    line where none reaches the threshold."""
    if len(peaks) == 0:
        raise NoBeadsError(
            f"No beads found: no maximum of the filtered image reaches `threshold` = "
            f"{threshold:g} noise standard deviations (the strongest reaches "
            f"{float(resp.max()):.3g}). Lower `threshold`, or check `psf_radius` = {r:g} px."
        )
    strength = resp[peaks[:, 0], peaks[:, 1]].astype(np.float64)
    order = np.argsort(-strength, kind="stable")
    peaks, strength = peaks[order], strength[order]
    peaks, strength = merge_secondary_maxima(peaks, strength, r)
    return merge_one_psf(img, peaks, strength, r, sigma)


def _standing_out(threshold, sigma, img, r, pixel_sd, peaks, scales, strength):
    """The maxima that stand ``threshold`` noise sd above their local background, with their
    strength and amplitude. A maximum of the filter that does not is the gap between dark
    structures (absorbing blobs on a structured background), not a bead; a faint wide spot
    stands out only at a wider scale, and there above the upper quartile of its surroundings
    too (a gap between dark blobs only above their median)."""
    amplitude = peak_amplitude(img, peaks, int(np.ceil(r)))
    # a maximum of the filter that does not stand above the background is the gap
    # between dark structures (absorbing blobs on a structured background), not a bead
    # (a faint wide spot stands out only at a wider scale, and there above the upper
    # quartile of its surroundings too; a gap between dark blobs only above their median)
    excess = background_excess(img, peaks, r, pixel_sd, sigma=sigma)
    for wide in scales:
        excess = np.maximum(excess, background_excess(img, peaks, r, pixel_sd, sigma=wide,
                                                      quantile=75.0))
    above = excess >= threshold
    if not above.any():
        raise NoBeadsError(
            f"No beads found: none of the {len(peaks)} maxima of the filtered image stands "
            f"`threshold` = {threshold:g} noise sd above the local background (gaps between "
            f"dark structures). Check the image and `psf_radius` = {r:g} px.")
    peaks, strength, amplitude = peaks[above], strength[above], amplitude[above]
    return amplitude, strength, peaks


def flag_unusable(
    beads: Beads,
    image: np.ndarray,
    psf_radius: float,
    *,
    saturation: float | None,
    border: float,
    min_separation: float | None = None,
    neighbour_ratio: float = NEIGHBOUR_RATIO,
    neighbour_share: float | None = NEIGHBOUR_SHARE,
) -> Beads:
    """Set the status of beads that are saturated, at the border or crowded (in place).

    Only beads whose status is ``kept`` are re-examined, so statuses set by a user
    (e.g. a rejected outlier) are preserved. A bead is crowded (status "neighbour") when
    the other detections together add at least ``neighbour_share`` of the energy in its
    patch (:func:`~napari_psfspace.core.beads.overlap.neighbour_shares`, with the PSF's
    radial profile measured on the image's brightest detections), or, with
    ``min_separation``, when one lies closer than that (the paper's fixed rule). Neighbours
    are counted among all detections, whatever their status: a rejected bead still
    spoils its neighbour; only detections found to be background structure (status
    "structure", removed from the image) are not counted, and detections fainter than
    ``neighbour_ratio`` of the bead (core flux; peak amplitude for the fixed rule: a
    faint speck beside a bright bead changes its patch by less than the noise).

    Returns
    -------
    Beads
        The same object, for chaining.
    """
    from scipy.spatial import cKDTree

    pos = beads.positions
    h, w = image.shape
    keep = beads.status == KEPT
    if saturation is not None and len(pos):
        sat = saturated_cores(image, pos, psf_radius, saturation)
        beads.status[keep & sat] = SATURATED
        keep &= ~sat
    at_border = (
        (pos[:, 0] < border)
        | (pos[:, 1] < border)
        | (pos[:, 0] > h - 1 - border)
        | (pos[:, 1] > w - 1 - border)
    )
    beads.status[keep & at_border] = BORDER
    keep &= ~at_border
    real = np.flatnonzero(beads.status != STRUCTURE)
    if len(real) < 2 or not keep.any():
        return beads
    amp = beads.amplitude
    todo = np.flatnonzero(keep)
    crowded = np.zeros(len(todo), bool)
    if neighbour_share is None and min_separation is None:
        min_separation = spacing.min_separation(psf_radius)
    if neighbour_share is not None:
        share = patch_shares(image, pos, todo, real, psf_radius,
                             neighbour_ratio=neighbour_ratio)
        if share is not None:
            crowded |= share >= neighbour_share
        elif min_separation is None:  # no light to measure a profile on: the fixed rule
            min_separation = spacing.min_separation(psf_radius)
    if min_separation is not None:
        tree = cKDTree(pos[real])
        lists = tree.query_ball_point(pos[todo], np.nextafter(min_separation, 0))
        for j, (i, found) in enumerate(zip(todo, lists, strict=True)):
            near = real[np.asarray(found, dtype=np.intp)]
            near = near[near != i]
            if len(near) == 0:
                continue
            if neighbour_ratio > 0 and np.isfinite(amp[i]) and amp[i] > 0:
                a = amp[near]
                if not np.any(~np.isfinite(a) | (a >= neighbour_ratio * amp[i])):
                    continue
            crowded[j] = True
    beads.status[todo[crowded]] = NEIGHBOUR
    return beads


#: What to change when too few beads were detected.
DETECTION_ADVICE = ("Lower `threshold`, check `psf_radius`, or image a denser bead "
                    "slide.")
#: What to change when the beads were given (a table, a Points layer).
GIVEN_ADVICE = ("Give more beads (mark them on the beads layer), or leave `beads` out "
                "to detect them.")


def require_kept(beads: Beads, minimum: int, *, reason: str,
                 advice: str = DETECTION_ADVICE) -> None:
    """Raise :class:`NoBeadsError` when fewer than ``minimum`` beads are kept; its
    message ends with ``advice`` (:data:`GIVEN_ADVICE` for beads the user gave)."""
    n = int(np.count_nonzero(beads.kept))
    if n < minimum:
        raise NoBeadsError(
            f"Too few usable beads: {n} kept, need at least {minimum} {reason}. "
            f"{beads.summary()}. {advice}"
        )

