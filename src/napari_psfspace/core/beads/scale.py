"""The scale of the spots an image shows, and the PSF radius that follows from it.

A bead in focus is a small spot; out of focus it is a disk or a ring many pixels across
(every slice of a bead z-stack but one). Detection must work at the scale of the PSF the
image shows: a Laplacian of Gaussian much narrower than a ring finds each ring as several
spots along its edge, which then reject one another as neighbours.

* :func:`detection_image`: at low counts (a background of a few ADU) the noise is skewed
  and its filtered tail far heavier than its robust spread says, so a threshold in noise
  sd lets hundreds of noise bumps through on a slice of noise (``bench/bench_camera.py``).
  There the detection runs on the
  variance-stabilised image ``2 sqrt(x - m + 3/8)`` (Anscombe; ``m`` the image's floor).
* :func:`characteristic_scale`: Lindeberg's scale selection on a few spots (windows about
  them): the scale at which their amplitude-normalised response ``-sigma^2 LoG`` is
  largest, where it is significant (a Gaussian spot of sd ``s``: ``sigma = s``; a thin
  ring of radius ``R``: ``sigma = 1.14 R``, where its centre, not its edge, responds).
  :func:`~napari_psfspace.core.beads.detect.detect_beads` moves to it when it is well
  above ``r / 4``.
* :func:`spot_scale` finds the scale on the whole image without a radius to start from
  (an image pyramid: coarse scales on binned copies; one vote per PSF: a ring's centre
  claims the spots along its edge; a spot must stand out at three neighbouring scales).
* :func:`suggest_psf_radius` measures, around spots found at that scale, the radius
  that encloses most of their energy within the signal's extent, on each spot's own
  pixels (those nearer it than any other spot: a neighbour is not its halo), above a
  plane fitted to its surroundings (a gradient is not a halo either), within
  :data:`SEARCH_SCALES` scales of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from ..common.errors import PsfSpaceError
from ..common.validate import as_image
from .spikes import (
    QUANTISATION_VARIANCE,
    find_spikes,
    inpaint_pixels,
    is_integer_valued,
    pixel_noise_sd,
)

#: Integer images whose background noise sd is below this (ADU) are treated as counts:
#: detection runs on the variance-stabilised image (:func:`detection_image`).
LOW_COUNT_SD = 3.0
#: A spot must stand out at this many neighbouring scales (a factor sqrt(2) apart) of
#: :func:`spot_scale`.
PERSISTENCE = 3
#: Scales tried around a starting scale, as factors (:func:`characteristic_scale`).
SCALE_FACTORS = (0.71, 1.0, 1.41, 2.0, 2.83, 4.0)
#: :func:`suggest_psf_radius` looks this many spot scales around each spot (and at least
#: :data:`MIN_SEARCH` pixels): far enough for the wings of a spot in focus, near enough
#: that a slight error of the background does not add up to a halo.
SEARCH_SCALES = 12.0
MIN_SEARCH = 24
#: :func:`suggest_psf_radius`: the model's radius over the spots' visible radius. One
#: bead shows its PSF down to its own noise; the model learns from all the beads at once
#: and still sees the wings below it (rings, the slow tail of an Airy pattern), so a
#: model cut at the visible radius is worse than a wider one. The factor comes from a
#: sweep of the radius on simulated scenes of two optics codes (aberration-free to
#: strong, bright and faint, the error against the true PSF) and on the measured stacks
#: (the held-out error): ``bench/bench_radius_sweep.py``.
WINGS = 1.5
#: A wider radius is suggested only while it keeps this fraction of the beads kept at
#: the visible radius (beads must be isolated at the radius: a dense field loses them).
KEEP_FRACTION = 0.5


def detection_image(image: np.ndarray, *, integer: bool, noise_sd: float
                    ) -> tuple[np.ndarray, bool, float]:
    """The image detection filters: the variance-stabilised image at low counts.

    Parameters
    ----------
    image : ndarray of shape (M, N), floating
    integer : bool
        The pixel values are integers (counts, ADU).
    noise_sd : float
        The background's pixel noise sd, image units
        (:func:`~napari_psfspace.core.beads.spikes.pixel_noise_sd`).

    Returns
    -------
    image : ndarray of shape (M, N), float32
        ``2 sqrt(x - m + 3/8)`` with ``m`` the 0.1 % quantile (the image's floor: the
        camera offset), or the image itself.
    stabilised : bool
        Whether the transform was applied (integer values, ``noise_sd`` below
        :data:`LOW_COUNT_SD`).
    sd_floor : float
        The least pixel noise sd in the returned image's units: the rounding of integer
        values (``sqrt(1/12)`` ADU), through the transform's slope at the background
        when it was applied (an image of ones and a few twos has a robust spread of 0:
        its noise is not 0); 0 for floating images.
    """
    img = np.asarray(image, dtype=np.float32)
    rounding = float(np.sqrt(QUANTISATION_VARIANCE)) if integer else 0.0
    if not integer or noise_sd >= LOW_COUNT_SD:
        return img, False, rounding
    step = max(1, int(np.sqrt(img.size / 250_000)))
    sample = img[::step, ::step]
    floor = float(np.percentile(sample, 0.1))
    level = float(np.median(sample)) - floor
    out = np.maximum(img - floor, 0.0)
    out += 3.0 / 8.0
    np.sqrt(out, out=out)
    out *= 2.0
    return out, True, rounding / float(np.sqrt(max(level, 0.0) + 3.0 / 8.0))


def _normalised(resp: np.ndarray, floor: float = 0.0) -> tuple[float, float]:
    """Median and robust sd (MAD, at least ``floor``) of a response."""
    step = max(1, int(np.sqrt(resp.size / 250_000)))
    sample = resp[::step, ::step]
    med = float(np.median(sample))
    mad = 1.4826 * float(np.median(np.abs(sample - med)))
    mad = max(mad, floor)
    if not np.isfinite(mad) or mad <= 0:
        mad = float(sample.std()) or 1.0
    return med, mad


def characteristic_scale(image: np.ndarray, peaks: np.ndarray, sigma0: float, *,
                         factors=SCALE_FACTORS, max_sigma: float | None = None,
                         noise_sd: float | None = None, threshold: float = 8.0
                         ) -> tuple[float, np.ndarray]:
    """The scale of the spots at ``peaks``: where their amplitude-normalised response is
    largest, over ``sigma0 * factors``.

    Each spot's response at scale ``sigma`` is the largest ``-sigma^2 LoG`` within
    ``sigma`` of its peak (a ring found on its edge at a small scale responds at its
    centre at its own), counted only where it stands ``threshold`` times its noise sd
    out (``noise_sd`` times the filter's norm: at low signal the noise's own response
    dominates the smallest scales); the scale chosen maximises the median over the
    spots. Computed on windows around the peaks only.

    Parameters
    ----------
    image : ndarray of shape (M, N)
        The image (not variance-stabilised: the amplitudes must be the image's).
    peaks : ndarray of shape (K, 2), int
        Spots (row, column), strongest first.
    sigma0 : float
        Starting scale, pixels.
    factors : sequence of float
        Scales tried, relative to ``sigma0``.
    max_sigma : float, optional
        Largest scale tried.
    noise_sd : float, optional
        The image's pixel noise sd; None: every response counts.
    threshold : float
        Significance, in noise sd of the response.

    Returns
    -------
    sigma : float
        The characteristic scale, pixels (``sigma0`` without peaks).
    responses : ndarray of shape (len(factors),)
        The median response at each scale (NaN where not tried).
    """
    from .detect import log_kernel_norm

    sigmas = sigma0 * np.asarray(factors, float)
    sigmas = np.maximum(sigmas, 0.7)
    if max_sigma is not None:
        sigmas = np.where(sigmas <= max_sigma, sigmas, np.nan)
    peaks = np.asarray(peaks, int).reshape(-1, 2)
    if len(peaks) == 0 or not np.isfinite(sigmas).any():
        return float(sigma0), np.full(len(sigmas), np.nan)
    h, w = image.shape
    out = np.full((len(peaks), len(sigmas)), np.nan)
    for k, s in enumerate(sigmas):
        if not np.isfinite(s):
            continue
        # a window of 5 scales about each peak, block-averaged so that the scale is at
        # least 1.5 binned pixels (the cost stays that of a small scale)
        b = max(1, int(s / 1.5))
        half = b * (int(np.ceil(5 * s / b)) + 1)
        sb = s / b
        noise = None if noise_sd is None else noise_sd * log_kernel_norm(sb) / b
        for i, (y, x) in enumerate(peaks):
            y0, y1, x0, x1 = max(0, y - half), min(h, y + half + b), max(0, x - half), \
                min(w, x + half + b)
            win = np.asarray(image[y0:y1, x0:x1], np.float64)
            win = block_mean(win, b)
            if min(win.shape) < 3:
                continue
            edge = np.concatenate([win[0], win[-1], win[1:-1, 0], win[1:-1, -1]])
            resp = -(sb**2) * ndi.gaussian_laplace(win - float(np.median(edge)), sb,
                                                   mode="nearest")
            yy, xx = np.ogrid[:win.shape[0], :win.shape[1]]
            d2 = (yy - (y - y0) / b) ** 2 + (xx - (x - x0) / b) ** 2
            value = float(resp[d2 <= max(1.0, sb) ** 2].max())
            if noise is None or value >= threshold * noise:
                out[i, k] = value
    counted = np.isfinite(out)
    if not counted.any():
        return float(sigma0), np.full(len(sigmas), np.nan)
    med = np.array([np.median(out[counted[:, k], k]) if counted[:, k].sum() >= max(
        1, counted.any(axis=1).sum() // 2) else np.nan for k in range(len(sigmas))])
    if not np.isfinite(med).any():
        return float(sigma0), med
    best = int(np.nanargmax(med))
    return float(sigmas[best]), med


@dataclass(frozen=True)
class SpotScale:
    """The spots of an image at their own scale (:func:`spot_scale`).

    Attributes
    ----------
    sigma : float
        Characteristic scale (pixels): the Laplacian-of-Gaussian scale at which the
        strongest spots respond most.
    spots : ndarray of shape (K, 2)
        The strongest spots at that scale (row, column), pixels.
    all_spots : ndarray of shape (L, 2)
        Every maximum above the threshold at that scale (the spots' neighbours).
    strength : ndarray of shape (K,)
        Their response in noise sd.
    stabilised : bool
        The detection ran on the variance-stabilised image (low counts).
    responses : dict
        Scale -> median amplitude-normalised response of that scale's strongest spots.
    """

    sigma: float
    spots: np.ndarray
    strength: np.ndarray
    stabilised: bool
    responses: dict
    all_spots: np.ndarray


def block_mean(img: np.ndarray, b: int) -> np.ndarray:
    if b == 1:
        return img
    h, w = (img.shape[0] // b) * b, (img.shape[1] // b) * b
    return img[:h, :w].reshape(h // b, b, w // b, b).mean(axis=(1, 3))


def _prepare(image) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """The image as float32 with its hot pixels inpainted, the detection image, its
    pixel noise sd floor and whether it was stabilised (:func:`detection_image`)."""
    raw = np.asarray(image)
    img = as_image(raw, dtype=np.float32)
    integer = is_integer_valued(raw)
    sd = pixel_noise_sd(raw, integer=integer)
    spikes = find_spikes(img, noise_sd=sd, integer=integer)
    if len(spikes):
        img = inpaint_pixels(img, spikes)
    det, stabilised, floor = detection_image(img, integer=integer, noise_sd=sd)
    return img, det, floor, stabilised


def spot_scale(image, *, threshold: float = 8.0, n_spots: int = 24,
               max_sigma: float | None = None, max_candidates: int = 300) -> SpotScale:
    """Find the spots of an image at their own scale, without a radius to start from.

    Scales ``1, 1.41, 2, ...`` pixels up to ``max_sigma`` (default a sixteenth of the
    smaller side); the coarse ones on block-averaged copies of the image (the scale at
    least 1.4 binned pixels). At every scale the maxima of the noise-normalised response
    above ``threshold`` are candidate spots (at most ``max_candidates``, strongest
    first). Each candidate's own scale is where its amplitude-normalised response
    ``-sigma^2 LoG`` (the largest within ``sigma`` of it) is largest (Lindeberg's
    selection); the image's scale is the median over the candidates, each counted once
    (candidates that reach their maximum at the same place and scale are one spot), so
    that isolated beads decide it and a few merged pairs or aggregates cannot.

    Raises
    ------
    NoBeadsError
        No maximum stands ``threshold`` noise sd out at any scale.
    """
    from .detect import NoBeadsError, local_peaks, log_kernel_norm

    img, det, floor, stabilised = _prepare(image)
    h, w = img.shape
    smax = float(max_sigma) if max_sigma else max(2.0, min(h, w) / 16.0)
    levels = []  # (sigma, binning, amplitude-normalised response, its median)
    candidates = []  # (row, column, strength)
    k = 0
    while True:
        s = float(2 ** (k / 2))
        k += 1
        if s > smax:
            break
        b = max(1, int(s / 1.4))
        x = block_mean(det, b)
        if min(x.shape) < 8:
            break
        sb = s / b
        resp = -(sb**2) * ndi.gaussian_laplace(x.astype(np.float32), sb, mode="reflect")
        med, mad = _normalised(resp, floor * log_kernel_norm(sb) / b)
        norm = (resp - med) / mad
        if stabilised:  # significance on the stabilised image, the scale on the image
            resp = -(sb**2) * ndi.gaussian_laplace(block_mean(img, b).astype(np.float32), sb,
                                                   mode="reflect")
            med = float(np.median(resp[::4, ::4]))
        size = 2 * int(np.ceil(sb)) + 1
        levels.append((s, b, ndi.maximum_filter(resp - med, size=size, mode="nearest"),
                       ndi.maximum_filter(norm, size=size, mode="nearest")))
        peaks = local_peaks(norm, max(1, int(round(2 * sb))), threshold)
        edge = int(np.ceil(sb))
        if len(peaks):
            inside = np.all((peaks >= edge) & (peaks < np.array(x.shape) - edge), axis=1)
            peaks = peaks[inside]
        for py, px in peaks[:max_candidates]:
            candidates.append(((py + 0.5) * b - 0.5, (px + 0.5) * b - 0.5, norm[py, px]))
    if not candidates:
        raise NoBeadsError(
            f"No spot stands out of the noise at any scale from 1 to {smax:.3g} px (threshold "
            f"{threshold:g} noise sd): no beads to measure. Check the image or the slice.")
    cand = np.array(candidates)
    cand = cand[np.argsort(-cand[:, 2], kind="stable")][:max_candidates]
    # each candidate's response at every scale (the largest within that scale of it):
    # amplitude-normalised (its scale) and noise-normalised (where it is significant)
    table = np.empty((len(cand), len(levels)))
    signif = np.empty((len(cand), len(levels)))
    for j, (_, b, near, near_n) in enumerate(levels):
        iy = np.clip(np.rint((cand[:, 0] + 0.5) / b - 0.5).astype(int), 0, near.shape[0] - 1)
        ix = np.clip(np.rint((cand[:, 1] + 0.5) / b - 0.5).astype(int), 0, near.shape[1] - 1)
        table[:, j] = near[iy, ix]
        signif[:, j] = near_n[iy, ix]
    sig = signif >= threshold
    # a spot is significant at three neighbouring scales (a factor 2) at least: a noise
    # bump stands out at one or two of the smallest (at low counts, where the noise is
    # skewed, and on a camera's noisy first frame); a PSF over a range of scales
    if sig.shape[1] >= PERSISTENCE:
        lasting = np.zeros(len(sig), bool)
        for k in range(sig.shape[1] - PERSISTENCE + 1):
            lasting |= sig[:, k:k + PERSISTENCE].all(axis=1)
    else:
        lasting = sig.any(axis=1)
    if not lasting.any():
        raise NoBeadsError(
            f"No spot stands out of the noise at {PERSISTENCE} neighbouring scales from 1 to "
            f"{smax:.3g} px (threshold {threshold:g} noise sd): no beads to measure. Check "
            "the image or the slice.")
    cand, table, sig = cand[lasting], table[lasting], sig[lasting]
    # its scale: where its amplitude-normalised response is largest, among the scales at
    # which it is significant (at low signal the noise's own response dominates the
    # smallest scales)
    own = np.argmax(np.where(sig, table, -np.inf), axis=1)
    sigmas = np.array([lv[0] for lv in levels])
    # one spot, one vote: candidates at the same place with the same scale are one
    keyed = {}
    for i in range(len(cand)):
        s = sigmas[own[i]]
        key = (own[i], int(cand[i, 0] // max(1.0, s)), int(cand[i, 1] // max(1.0, s)))
        keyed.setdefault(key, i)
    unique = np.array(sorted(keyed.values()))
    # one PSF, one vote: a spot of a large scale (a ring, at its centre) claims the
    # smaller ones within its reach (the same ring found on its edge)
    from scipy.spatial import cKDTree

    order = unique[np.argsort(-sigmas[own[unique]], kind="stable")]
    claimed = np.zeros(len(cand), bool)
    tree = cKDTree(cand[unique, :2])
    for i in order:
        if claimed[i]:
            continue
        s_i = sigmas[own[i]]
        for k2 in tree.query_ball_point(cand[i, :2], 1.5 * s_i):
            other = unique[k2]
            if other != i and sigmas[own[other]] < s_i:
                claimed[other] = True
    unique = unique[~claimed[unique]]
    sigma = float(np.exp(np.median(np.log(sigmas[own[unique]]))))
    # snap to the ladder; the spots: those of about that scale, strongest first
    best = int(np.argmin(np.abs(np.log(sigmas / sigma))))
    sigma = float(sigmas[best])
    near_scale = unique[np.abs(own[unique] - best) <= 1]
    spots = cand[near_scale]
    responses = {float(sv): float(np.median(table[unique, j]))
                 for j, sv in enumerate(sigmas)}
    return SpotScale(sigma, spots[:n_spots, :2], spots[:n_spots, 2], stabilised, responses,
                     cand[unique, :2])


def _spot_radius(win: np.ndarray, own: np.ndarray, energy: float) -> int | None:
    """The radius enclosing ``energy`` of a spot's energy within its signal's extent,
    from its azimuthal median profile over its ``own`` pixels, above a plane fitted to
    the outer part of them (None when it cannot be measured)."""
    room = win.shape[0] // 2
    yy, xx = np.mgrid[-room:room + 1, -room:room + 1]
    dist = np.hypot(yy, xx)
    ring = np.rint(dist).astype(int)
    # the background: a plane through the outer part of the spot's own pixels (on one
    # side only where a neighbour is near: a gradient must not read as a halo)
    reach = int(ring[own].max())
    outer = own & (ring >= max(2, int(0.6 * reach)))
    if outer.sum() < 12:
        return None
    design = np.column_stack([np.ones(outer.sum()), yy[outer], xx[outer]])
    vals = win[outer]
    use = np.ones(len(vals), bool)
    for _ in range(2):  # least squares, then without the outliers (a neighbour's wing)
        coef, *_ = np.linalg.lstsq(design[use], vals[use], rcond=None)
        res = vals - design @ coef
        sd = 1.4826 * float(np.median(np.abs(res[use] - np.median(res[use]))))
        trimmed = np.abs(res) <= 3 * sd
        if sd <= 0 or trimmed.sum() < 12:
            break
        use = trimmed
    flat = win - (coef[0] + coef[1] * yy + coef[2] * xx)
    labels = np.where(own & (ring <= room), ring, -1)
    count = np.bincount(labels[labels >= 0], minlength=room + 1)[:room + 1]
    if count[0] == 0:
        return None
    prof = np.full(room + 1, np.nan)  # NaN where fewer than 3 own pixels
    idx = np.union1d(np.flatnonzero(count >= 3), [0])
    prof[idx] = np.asarray(ndi.median(flat, labels=labels, index=idx))
    ring_sd = 1.25 * sd / np.sqrt(np.maximum(count, 1))
    strong = prof >= 3 * ring_sd
    if not strong.any():
        return None
    # the signal's extent: where the profile first falls back to the noise after its
    # first significant ring (a faint ring out of focus has a dark centre: its profile
    # starts in the noise)
    first = int(np.argmax(strong))
    low = np.flatnonzero(~strong[first:])
    extent = first + int(low[0]) if len(low) else room
    if extent < 1:
        return None
    full = 2 * np.pi * np.maximum(np.arange(extent + 1), 0.5)  # a whole ring's pixels
    full[0] = 1.0
    enclosed = np.cumsum(np.clip(prof[:extent + 1], 0, None) * full)
    return int(np.searchsorted(enclosed, energy * enclosed[-1]))


#: Spots whose energy radius exceeds this many times the median spot's do not set the
#: radius (the defocused slices of the measured stacks: ``bench/RESULTS.md``).
MAX_OVER_MEDIAN = 2.5


def suggest_psf_radius(image, *, n_beads: int = 20, energy: float = 0.97,
                       max_radius: float | None = None, wings: float = WINGS) -> float:
    """Suggest the PSF radius ``r`` (pixels) for a model learnt from an image's spots.

    The spots are found at their own scale ``sigma`` (:func:`spot_scale`), so that a ring
    out of focus is one spot at its centre, not several on its edge. For the strongest few
    in each cell of a 4 x 4 tiling of the field (the PSF varies over the field), the
    azimuthal median profile above the local background (a plane through the outer part
    of the window) gives the enclosed energy, on the pixels nearer that spot than any
    other (so that neighbours do not count as its halo), within
    :data:`SEARCH_SCALES` scales of it; a spot's radius is where the energy reaches
    ``energy`` of the total within the signal's extent (the profile above 3 noise sd of a
    ring median). The radius must bound the widest PSFs of the field, so the 75th
    percentile over the spots, plus one pixel, is the spots' *visible radius*; spots
    wider than :data:`MAX_OVER_MEDIAN` times the median spot (aggregates, dust,
    structure) do not count.

    The model is learnt from all the beads at once and still sees the wings below one
    bead's noise, so the suggestion is ``wings`` times the visible radius
    (:data:`WINGS`), or, where that wider radius would keep fewer than
    :data:`KEEP_FRACTION` of the beads isolated at the visible radius, halfway to it,
    else the visible radius itself.

    Parameters
    ----------
    image : array_like of shape (M, N)
    n_beads : int
        About how many spots are used (spread over the field).
    energy : float
        Enclosed-energy fraction that defines a spot's radius.
    max_radius : float, optional
        Largest radius considered; default ``min(M, N) / 8``.
    wings : float
        The suggestion over the visible radius (1: the visible radius, e.g. to detect
        beads rather than to model them).

    Returns
    -------
    float
        Suggested radius in pixels, at least 3.

    Raises
    ------
    NoBeadsError
        No spot stands out of the noise.
    """
    from scipy.spatial import cKDTree

    from ..common.validate import check_int, check_positive
    from .detect import NoBeadsError

    n_beads = check_int(n_beads, "n_beads", minimum=1)
    if not 0 < check_positive(energy, "energy") < 1:
        raise ValueError(f"`energy` must be a fraction in (0, 1), got {energy!r}.")
    img, _, _, _ = _prepare(image)
    h, w = img.shape
    rmax = int(max_radius or max(6, min(h, w) // 8))
    try:
        found = spot_scale(image, max_sigma=max(1.0, rmax / 2.0))
    except NoBeadsError as exc:
        raise NoBeadsError(f"{exc} No `psf_radius` can be suggested: give it yourself if "
                           "the image does hold beads.") from None
    search = int(min(rmax, max(MIN_SEARCH, np.ceil(SEARCH_SCALES * found.sigma))))
    spots = np.rint(found.spots).astype(int)
    # the strongest few in each cell of a 4 x 4 tiling: the whole field counts
    cell = (spots[:, 0] * 4 // h) * 4 + spots[:, 1] * 4 // w
    order = np.lexsort((-found.strength, cell))
    rank = np.arange(len(order)) - np.searchsorted(cell[order], cell[order])
    chosen = order[rank < max(1, n_beads // 16 + 1)]
    tree = cKDTree(found.all_spots) if len(found.all_spots) > 1 else None
    radii = []
    for y, x in spots[chosen]:
        room = int(min(search, y, x, h - 1 - y, w - 1 - x))
        if room < 4:
            continue
        win = img[y - room:y + room + 1, x - room:x + room + 1].astype(np.float64)
        yy, xx = np.mgrid[-room:room + 1, -room:room + 1]
        own = np.ones(win.shape, bool)
        if tree is not None:  # the pixels nearer this spot than any other
            for j in tree.query_ball_point((y, x), 2 * room + 1):
                dy, dx = found.all_spots[j][0] - y, found.all_spots[j][1] - x
                if dy * dy + dx * dx >= 1.0:
                    own &= yy**2 + xx**2 <= (yy - dy) ** 2 + (xx - dx) ** 2
        r = _spot_radius(win, own, energy)
        if r is not None:
            radii.append(r)
    if not radii:
        raise NoBeadsError("Could not measure the width of any bright spot: give "
                           "`psf_radius` yourself.")
    radii = np.asarray(radii, float)
    # a spot far wider than the median spot is an aggregate, dust or structure, not a
    # bead: on a defocused slice of few beads one such spot set the radius (RESULTS.md)
    radii = radii[radii <= MAX_OVER_MEDIAN * np.median(radii)]
    visible = float(max(3.0, np.ceil(np.percentile(radii, 75)) + 1.0))
    if not wings > 1.0:
        return visible
    return _wider_radius(image, visible, float(wings), rmax)


def _wider_radius(image, visible: float, wings: float, rmax: int) -> float:
    """``wings x visible`` (or halfway to it) where it keeps :data:`KEEP_FRACTION` of
    the beads kept at ``visible``, else ``visible``."""
    from ..common.errors import PsfSpaceError
    from .detect import detect_beads

    def kept(r: float) -> int:
        try:
            return int(np.count_nonzero(detect_beads(image, r).kept))
        except PsfSpaceError:
            return 0

    base = kept(visible)
    for factor in (wings, (1.0 + wings) / 2):
        r = float(min(np.ceil(factor * visible), rmax))
        if r <= visible:
            break
        if base and kept(r) >= KEEP_FRACTION * base:
            return r
    return visible


#: A slice's suggested radius beyond this factor of the in-focus slice's is explained.
SLICE_RATIO = 1.5


def radius_against_focus(stack, index: int, radius: float, *, focus: int | None = None,
                         focus_radius: float | None = None) -> str:
    """Why a slice's radius departs from the in-focus slice's by more than
    :data:`SLICE_RATIO`, in one sentence; empty when it does not (or is the focus).

    Parameters
    ----------
    stack : ndarray of shape (Z, M, N)
    index : int
        The slice the radius is for.
    radius : float
        Its suggested radius, pixels.
    focus, focus_radius : optional
        The best-focus slice and its suggested radius, where already known.
    """
    from .detect import detect_beads
    from .focus import best_focus_index

    arr = np.asarray(stack)
    focus = best_focus_index(arr) if focus is None else int(focus)
    if focus == index:
        return ""
    try:
        r_focus = suggest_psf_radius(arr[focus]) if focus_radius is None else focus_radius
    except PsfSpaceError:
        return ""
    ratio = float(radius) / r_focus
    if 1 / SLICE_RATIO <= ratio <= SLICE_RATIO:
        return ""

    def count(image, r):
        try:
            b = detect_beads(image, r)
            return int(np.count_nonzero(b.kept)), len(b)
        except PsfSpaceError:
            return 0, 0

    kept, found = count(arr[index], radius)
    kept_f, found_f = count(arr[focus], r_focus)
    return (f"slice {index} is {abs(index - focus)} slice(s) from the best focus (slice "
            f"{focus}, radius {r_focus:g} px, {kept_f} of {found_f} beads kept): its "
            f"beads are {'wider' if ratio > 1 else 'narrower'} there, {ratio:.2f}x "
            f"({radius:g} px, {kept} of {found} beads kept); pass --psf-radius to choose "
            "another.")


__all__ = ["KEEP_FRACTION", "LOW_COUNT_SD", "MAX_OVER_MEDIAN", "SLICE_RATIO",
           "WINGS", "SpotScale", "characteristic_scale", "detection_image",
           "radius_against_focus", "spot_scale", "suggest_psf_radius"]
