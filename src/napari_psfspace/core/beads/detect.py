"""Rough bead detection and rejection of beads that cannot give a clean PSF patch.

Paper, Appendix A: beads are the maxima of the Laplacian of a smoothed image above a
threshold; beads closer than ``r`` to the border or ``2 r`` to another bead are
rejected, so every kept patch holds one isolated PSF. Here a neighbour is judged by the
light it adds to the patch (:mod:`~napari_psfspace.core.beads.overlap`), not by a fixed
distance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from ..common import spacing
from ..common.errors import NoBeadsError
from ..common.progress import check_halt
from ..common.validate import as_array, as_image, check_positive, check_psf_radius, check_saturation
from .log import local_peaks, log_response
from .overlap import NEIGHBOUR_SHARE, patch_shares
from .saturation import saturated_cores
from .scale import block_mean, characteristic_scale, detection_image, prepare, spot_scale
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
#: Detection moves to the scale of the spots the image shows when that scale is at least
#: this many times the default ``r / 4`` (rings out of focus; a spot in focus keeps it).
RESCALE_FACTOR = 1.4
#: The scale is judged on this many of the strongest maxima at ``r / 4``; with fewer (a
#: few faint wide spots, each found there as noise on its edge, or not at all) it is
#: searched over all scales (:func:`~napari_psfspace.core.beads.scale.spot_scale`).
MIN_SCALE_PEAKS = 16
#: Where a quarter of the maxima found stand less than this many times the threshold
#: out, the beads are faint (more stand just below it): wider scales are searched too.
FAINT_STRENGTH = 2.0


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

    Notes
    -----
    The noise level of the filtered image is its robust (MAD) spread, never below what
    the rounding of an integer image gives (variance 1/12 ADU^2 per pixel): on a nearly
    constant integer background the MAD collapses towards zero and every one-count bump
    would otherwise stand many "noise sd" out. At low counts (integer values, background
    noise below :data:`~napari_psfspace.core.beads.scale.LOW_COUNT_SD` ADU) the filter
    runs on the variance-stabilised image
    (:func:`~napari_psfspace.core.beads.scale.detection_image`): there the noise is skewed
    and its filtered tail far heavier than its spread says.

    Raises
    ------
    NoBeadsError
        When nothing stands above the threshold; the message gives the strongest
        response found so that the user knows how far to lower ``threshold``.
    """
    raw = np.asarray(as_array(image, "image"))
    img = as_image(raw, dtype=np.float32, copies=DETECT_IMAGES)
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
    resp = log_response(det, sigma, pixel_sd_floor=floor)
    peaks = local_peaks(resp, max(1, int(round(r / 2))), threshold)
    scales = []  # the wider scales that added maxima
    if auto_sigma:
        # the scale of the PSF the image shows: a ring out of focus responds at its centre
        # at a scale near its radius, not at r / 4 (where it is several spots on its edge)
        if len(peaks) >= MIN_SCALE_PEAKS:  # the scale of the strongest maxima
            found, _ = characteristic_scale(img, peaks[:MIN_SCALE_PEAKS], sigma, max_sigma=r,
                                            noise_sd=pixel_sd, threshold=threshold)
        else:  # faint wide spots stand out only at their own scale: search all scales
            try:
                found = spot_scale(raw, threshold=threshold, max_sigma=r).sigma
            except NoBeadsError:
                found = sigma
        wider = []
        if found >= RESCALE_FACTOR * sigma:
            sigma = found
            resp = log_response(det, sigma, pixel_sd_floor=floor)
            peaks = local_peaks(resp, max(1, int(round(max(r / 2, sigma)))), threshold)
            wider = [np.sqrt(2.0) * sigma]
        if len(peaks) == 0 or np.percentile(resp[peaks[:, 0], peaks[:, 1]], 25) < \
                FAINT_STRENGTH * threshold:
            # faint beads: the weakest found stand near the threshold, so others stand
            # just below it; a wider filter (about the whole disk) gains signal to noise
            wider = [np.sqrt(2.0) * sigma, 2.0 * sigma]
        for wide in wider:
            # a faint wide spot stands out most at a scale above the one that locates it
            # (the filter then matches its whole disk): add what only a coarser scale finds
            wide = min(wide, float(r))
            if wide < 1.2 * sigma:
                continue
            resp_wide = log_response(det, wide, pixel_sd_floor=floor)
            sep = max(1, int(round(max(r / 2, wide))))
            more = local_peaks(resp_wide, sep, threshold)
            if len(more) and len(peaks):
                from scipy.spatial import cKDTree

                d, _ = cKDTree(peaks).query(more)
                more = more[d > sep]
            if len(more):
                resp = np.maximum(resp, resp_wide)
                peaks = np.concatenate([peaks, more]) if len(peaks) else more
                scales.append(wide)
    if len(peaks) == 0:
        raise NoBeadsError(
            f"No beads found: no maximum of the filtered image reaches `threshold` = "
            f"{threshold:g} noise standard deviations (the strongest reaches "
            f"{float(resp.max()):.3g}). Lower `threshold`, or check `psf_radius` = {r:g} px."
        )
    strength = resp[peaks[:, 0], peaks[:, 1]].astype(np.float64)
    order = np.argsort(-strength, kind="stable")
    peaks, strength = peaks[order], strength[order]
    peaks, strength = _merge_secondary_maxima(peaks, strength, r)
    peaks, strength = merge_one_psf(img, peaks, strength, r, sigma)

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
    beads = Beads(peaks.astype(np.float64), strength, amplitude=amplitude,
                  hot_pixels=spikes if hot_pixels else None)
    flag_unusable(beads, img, r, saturation=saturation, border=border,
                  min_separation=min_separation, neighbour_ratio=neighbour_ratio,
                  neighbour_share=neighbour_share)
    return beads


def background_excess(image: np.ndarray, peaks: np.ndarray, r: float, noise_sd: float,
                      *, sigma: float | None = None, quantile: float = 50.0) -> np.ndarray:
    """How far each maximum stands above the local background, in noise sd, shape (M,).

    The image smoothed by a Gaussian of ``sigma / 2`` (``sigma``: the detection's scale,
    default ``r / 4``; one pixel of a faint wide spot is mostly noise), at the maximum,
    minus a background map (the median over about ``4.5 r`` of the image binned by
    ``r / 2``: beads, and dark blobs, cover a minority of it; or another ``quantile`` of
    it, percent), over the smoothed image's noise ``noise_sd / (sqrt(4 pi) sigma / 2)``.
    A bead stands out; the gap between dark absorbing blobs is a maximum of the filter
    only because of what surrounds it, at the level of the background.
    """
    if len(peaks) == 0:
        return np.zeros(0)
    img = np.asarray(image, np.float32)
    s = max(0.5, (r / 4.0 if sigma is None else float(sigma)) / 2.0)
    b = max(1, int(r // 2))
    small = block_mean(img, b)
    p = np.rint(np.asarray(peaks, np.float64)).astype(int)
    iy = np.clip(p[:, 0] // b, 0, small.shape[0] - 1)
    ix = np.clip(p[:, 1] // b, 0, small.shape[1] - 1)
    # the quantile of the 9 x 9 binned pixels around each maximum, and its Gaussian-smoothed
    # value from its own window (the whole image need not be filtered for a few hundred)
    from .centering import gather_windows

    bg = np.percentile(gather_windows(small, np.column_stack([iy, ix]).astype(np.float64), 4)
                       .reshape(len(p), -1), quantile, axis=1)
    half = int(np.ceil(3.0 * s))
    g = np.exp(-0.5 * (np.arange(-half, half + 1) / s) ** 2)
    kernel = np.outer(g, g) / g.sum() ** 2
    win = gather_windows(img, p.astype(np.float64), half)
    level = np.einsum("kij,ij->k", win.astype(np.float64), kernel) - bg
    sd = max(float(noise_sd), 1e-12) / (np.sqrt(4.0 * np.pi) * s)
    return (level / sd).astype(np.float64)


def peak_amplitude(image: np.ndarray, peaks: np.ndarray, half: int) -> np.ndarray:
    """Peak value above the median of the edge of a ``(2 half + 1)`` window, shape (M,)."""
    from .centering import gather_windows

    if len(peaks) == 0:
        return np.zeros(0)
    win = gather_windows(image, np.asarray(peaks, dtype=np.float64), half)
    edge = np.concatenate([win[:, 0, :], win[:, -1, :], win[:, 1:-1, 0], win[:, 1:-1, -1]],
                          axis=1)
    return (win[:, half, half] - np.median(edge, axis=1)).astype(np.float64)


def _merge_secondary_maxima(peaks, strength, r):
    """Drop weak maxima within ``r`` of a much stronger one (rings of one defocused PSF)."""
    from scipy.spatial import cKDTree

    if len(peaks) < 2:
        return peaks, strength
    tree = cKDTree(peaks)
    drop = np.zeros(len(peaks), dtype=bool)
    for i, j in sorted(tree.query_pairs(r)):
        # peaks are sorted by decreasing strength, so i is the stronger one
        if not drop[i] and strength[j] < 0.5 * strength[i]:
            drop[j] = True
    return peaks[~drop], strength[~drop]


def merge_one_psf(image: np.ndarray, peaks: np.ndarray, strength: np.ndarray, r: float,
                  sigma: float, *, saddle: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Merge maxima that one PSF makes: two maxima within ``2 r`` of each other joined by a
    path (straight, or around a ring's dark centre) along which the smoothed image stays
    at least ``saddle`` of the lower one's height above the local background (two arcs of
    a defocused ring; two separate spots dip towards the background between them). A
    group becomes one detection at its maxima's strength-weighted mean, with the
    strongest one's strength.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    peaks : ndarray of shape (K, 2), int
        Maxima, strongest first.
    strength : ndarray of shape (K,)
    r : float
        PSF radius, pixels.
    sigma : float
        Detection scale, pixels (the image is smoothed by it).

    Returns
    -------
    peaks, strength
        The merged maxima (rounded positions), strongest first.
    """
    check_halt()
    from scipy.spatial import cKDTree

    if len(peaks) < 2:
        return peaks, strength
    # within the neighbour distance 2 r: a ring wider than the radius suggested for it
    # (a corner bead's coma) is still one PSF; two beads that close are unusable anyway,
    # and they are merged only if joined
    pairs = sorted(cKDTree(peaks).query_pairs(2 * r))
    if not pairs:
        return peaks, strength
    h, w = image.shape
    half = int(np.ceil(2 * r + 3 * sigma))
    parent = np.arange(len(peaks))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    t = np.linspace(0.0, 1.0, 4 * int(np.ceil(r)) + 1)
    for i, j in pairs:
        mid = (peaks[i] + peaks[j]) // 2
        y0, x0 = max(0, mid[0] - half), max(0, mid[1] - half)
        win = np.asarray(image[y0:min(h, mid[0] + half + 1), x0:min(w, mid[1] + half + 1)],
                         np.float64)
        smooth = ndi.gaussian_filter(win, sigma / 2, mode="nearest")
        bg = float(np.percentile(smooth, 10))
        pi, pj = peaks[i] - np.array([y0, x0]), peaks[j] - np.array([y0, x0])
        line = pi[None, :] * (1 - t[:, None]) + pj[None, :] * t[:, None]
        along = ndi.map_coordinates(smooth, line.T, order=1, mode="nearest")
        low = min(along[0], along[-1]) - bg
        if low <= 0:
            continue
        joined = along.min() - bg >= saddle * low  # straight across
        if not joined:  # or around: two arcs of one ring, its dark centre between them
            lab, _ = ndi.label(smooth - bg >= saddle * low)
            joined = lab[tuple(pi)] != 0 and lab[tuple(pi)] == lab[tuple(pj)]
        if joined:
            a, b = root(i), root(j)
            parent[max(a, b)] = min(a, b)
    groups = np.array([root(i) for i in range(len(peaks))])
    if len(np.unique(groups)) == len(peaks):
        return peaks, strength
    keep = np.unique(groups)
    out = np.empty((len(keep), 2))
    for k, g in enumerate(keep):
        members = groups == g
        wgt = np.maximum(strength[members], 1e-12)
        out[k] = (peaks[members] * wgt[:, None]).sum(axis=0) / wgt.sum()
    st = np.array([strength[groups == g].max() for g in keep])
    order = np.argsort(-st, kind="stable")
    return np.rint(out[order]).astype(peaks.dtype), st[order]


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

