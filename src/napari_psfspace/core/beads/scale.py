"""The scale of the spots an image shows.

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

The PSF radius that follows from that scale is :mod:`.radius`'s.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from ..common.validate import as_array, as_image
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
    from .log import log_kernel_norm

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


@dataclass(frozen=True)
class Prepared:
    """An image made ready for detection (:func:`prepare`).

    Attributes
    ----------
    image : ndarray of shape (M, N), float32
        The image with its hot pixels inpainted.
    detection : ndarray of shape (M, N), float32
        The image the filters run on (:func:`detection_image`).
    sd_floor : float
        Its least pixel noise sd.
    stabilised : bool
        Whether it is the variance-stabilised image.
    integer : bool
        The pixel values are integers.
    noise_sd : float
        The background's pixel noise sd, image units.
    spikes : ndarray of shape (K, 2), int
        The hot pixels found (row, column).
    """

    image: np.ndarray
    detection: np.ndarray
    sd_floor: float
    stabilised: bool
    integer: bool
    noise_sd: float
    spikes: np.ndarray


class _Reuse:
    """What :func:`prepare` and :func:`spot_scale` computed on one image, kept while a
    :func:`reusing` block runs: the prepared image and the scale pyramid's levels."""

    def __init__(self, image) -> None:
        self.image = image
        self.prepared: Prepared | None = None
        self.levels: dict[int, tuple | None] = {}


_REUSE: ContextVar[_Reuse | None] = ContextVar("napari_psfspace_scale_reuse", default=None)


@contextmanager
def reusing(image):
    """Within the block, :func:`prepare`, :func:`spot_scale` and
    :func:`~napari_psfspace.core.beads.detect.detect_beads` called on this very object
    (``is``, unchanged meanwhile) prepare it and build its scale pyramid once: a radius
    suggestion detects the beads of one image at several radii. The results are those of
    the calls without the block; the arrays kept are read-only."""
    token = _REUSE.set(_Reuse(image))
    try:
        yield
    finally:
        _REUSE.reset(token)


def _reuse_for(image) -> _Reuse | None:
    memo = _REUSE.get()
    return memo if memo is not None and memo.image is image else None


def _read_only(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.flags.writeable = False


def prepare(image) -> Prepared:
    """The image as float32 with its hot pixels found and inpainted
    (:func:`~napari_psfspace.core.beads.spikes.find_spikes`), and the image detection
    filters (:func:`detection_image`).

    Parameters
    ----------
    image : array_like of shape (M, N)

    Returns
    -------
    Prepared
    """
    memo = _reuse_for(image)
    if memo is not None and memo.prepared is not None:
        return memo.prepared
    raw = np.asarray(as_array(image, "image"))
    img = as_image(raw, dtype=np.float32)
    integer = is_integer_valued(raw)
    sd = pixel_noise_sd(raw, integer=integer)
    spikes = find_spikes(img, noise_sd=sd, integer=integer)
    if len(spikes):
        img = inpaint_pixels(img, spikes)
    det, stabilised, floor = detection_image(img, integer=integer, noise_sd=sd)
    out = Prepared(img, det, floor, stabilised, integer, sd, spikes)
    if memo is not None:
        if img is raw:  # kept read-only: a copy, never the caller's own array
            img = img.copy()
            det = img if det is raw else det
            out = Prepared(img, det, floor, stabilised, integer, sd, spikes)
        _read_only(img, det, spikes)
        memo.prepared = out
    return out


def prepare_image(image) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """The image as float32 with its hot pixels inpainted, the detection image, its
    pixel noise sd floor and whether it was stabilised (:func:`prepare`)."""
    p = prepare(image)
    return p.image, p.detection, p.sd_floor, p.stabilised


def _level(k: int, prepared: Prepared) -> tuple | None:
    """Level ``k`` of :func:`spot_scale`'s pyramid (scale ``2^(k/2)`` px): ``(sigma,
    binning, near, near_n, norm)``, None where the binned image is too small."""
    from .log import log_kernel_norm

    memo = _REUSE.get()
    memo = memo if memo is not None and memo.prepared is prepared else None
    if memo is not None and k in memo.levels:
        return memo.levels[k]
    img, det, floor = prepared.image, prepared.detection, prepared.sd_floor
    s = float(2 ** (k / 2))
    b = max(1, int(s / 1.4))
    x = block_mean(det, b)
    out = None
    if min(x.shape) >= 8:
        sb = s / b
        resp = -(sb**2) * ndi.gaussian_laplace(x.astype(np.float32), sb, mode="reflect")
        med, mad = _normalised(resp, floor * log_kernel_norm(sb) / b)
        norm = (resp - med) / mad
        if prepared.stabilised:  # significance on the stabilised image, the scale on the image
            resp = -(sb**2) * ndi.gaussian_laplace(block_mean(img, b).astype(np.float32), sb,
                                                   mode="reflect")
            med = float(np.median(resp[::4, ::4]))
        size = 2 * int(np.ceil(sb)) + 1
        out = (s, b, ndi.maximum_filter(resp - med, size=size, mode="nearest"),
               ndi.maximum_filter(norm, size=size, mode="nearest"), norm)
        if memo is not None:
            _read_only(*out[2:])
    if memo is not None:
        memo.levels[k] = out
    return out


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
    prepared = prepare(image)
    stabilised = prepared.stabilised
    h, w = prepared.image.shape
    smax = float(max_sigma) if max_sigma else max(2.0, min(h, w) / 16.0)
    levels, cand = _candidates(prepared, threshold, max_candidates, smax)
    table, sig, cand = _lasting(cand, levels, threshold, smax)
    # its scale: where its amplitude-normalised response is largest, among the scales at
    # which it is significant (at low signal the noise's own response dominates the
    # smallest scales)
    own = np.argmax(np.where(sig, table, -np.inf), axis=1)
    sigmas = np.array([lv[0] for lv in levels])
    unique = _one_vote_each(cand, own, sigmas)
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


def _candidates(prepared, threshold, max_candidates, smax):
    """The scale ladder's levels and the candidate spots found on them, strongest first."""
    from ..common.errors import NoBeadsError
    from .log import local_peaks

    levels = []  # (sigma, binning, amplitude-normalised response, its median)
    candidates = []  # (row, column, strength)
    k = 0
    while True:
        if float(2 ** (k / 2)) > smax:
            break
        level = _level(k, prepared)
        k += 1
        if level is None:
            break
        s, b, near, near_n, norm = level
        sb = s / b
        levels.append((s, b, near, near_n))
        peaks = local_peaks(norm, max(1, int(round(2 * sb))), threshold)
        edge = int(np.ceil(sb))
        if len(peaks):
            inside = np.all((peaks >= edge) & (peaks < np.array(norm.shape) - edge), axis=1)
            peaks = peaks[inside]
        for py, px in peaks[:max_candidates]:
            candidates.append(((py + 0.5) * b - 0.5, (px + 0.5) * b - 0.5, norm[py, px]))
    if not candidates:
        raise NoBeadsError(
            f"No spot stands out of the noise at any scale from 1 to {smax:.3g} px (threshold "
            f"{threshold:g} noise sd): no beads to measure. Check the image or the slice.")
    cand = np.array(candidates)
    cand = cand[np.argsort(-cand[:, 2], kind="stable")][:max_candidates]
    return levels, cand


def _lasting(cand, levels, threshold, smax):
    """Each candidate's response at every scale and whether it is significant there;
    only the candidates significant at ``PERSISTENCE`` neighbouring scales at least."""
    from ..common.errors import NoBeadsError

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
    return table, sig, cand


def _one_vote_each(cand, own, sigmas):
    """The candidates that count, one per spot."""
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
    return unique


__all__ = ["LOW_COUNT_SD", "Prepared", "SpotScale", "characteristic_scale",
           "detection_image", "prepare", "prepare_image", "reusing", "spot_scale"]
