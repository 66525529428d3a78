"""The maxima detection finds, judged: the scales the beads show, maxima merged where they
are one PSF, and their height above the local background and their amplitude."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from ..common.errors import NoBeadsError
from ..common.progress import check_halt
from .log import local_peaks, log_response
from .scale import block_mean, characteristic_scale, spot_scale

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


def merge_secondary_maxima(peaks, strength, r):
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


def wider_scales(raw, img, det, peaks, resp, sigma, r, *, threshold, noise_sd, floor):
    """With the default scale ``r / 4``: the scale of the PSF the image shows (a ring out of
    focus responds at its centre at a scale near its radius, not at ``r / 4``, where it is
    several spots on its edge), and, for faint beads, the maxima only a wider scale finds.

    Returns the scale, the maxima, the response (the largest over the scales) and the
    wider scales that added maxima.
    """
    scales = []
    if len(peaks) >= MIN_SCALE_PEAKS:  # the scale of the strongest maxima
        found, _ = characteristic_scale(img, peaks[:MIN_SCALE_PEAKS], sigma, max_sigma=r,
                                        noise_sd=noise_sd, threshold=threshold)
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
    return sigma, peaks, resp, scales
