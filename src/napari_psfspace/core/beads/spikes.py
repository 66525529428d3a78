"""Hot pixels and cosmic rays: spots narrower than any optics can form.

A fluorescence image is the object seen through a band-limited optical transfer
function, sampled by pixels. However small the emitter, its image spreads over several
pixels: for an aberration-free widefield PSF integrated over square pixels, the third
brightest pixel of the 3 x 3 neighbourhood of a spot's maximum holds at least 54 % of
the maximum at Nyquist sampling (pixel ``lambda / (4 NA)``), 13 % at twice coarser
sampling and 10 % at 2.2 times (measured with the project's simulator over sub-pixel
offsets; ``tests/test_spikes.py``). A pixel that stands far above its surroundings while
its neighbourhood's third brightest pixel does not (one bright pixel, or two adjacent
ones, on a dark neighbourhood) is a hot pixel of the camera or a cosmic ray, not a bead.

Aberrations, defocus and the bead's own size only widen a spot, so the test is
conservative; only a camera sampling far coarser than Nyquist (more than ~2.2 times)
forms spots this sharp, and there beads and hot pixels cannot be told apart by shape.

Only one full-image filter runs (a 7 x 7 box mean): pixels standing ``k`` noise sd above
it are the candidates, and the local-maximum test, the ring median and the
neighbourhood order statistics are computed at those only.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from ..common.threads import filter_by_rows

#: Smallest ratio (third brightest pixel of the 3 x 3 neighbourhood above the local
#: background, over the maximum above it) that a band-limited spot sampled at up to
#: ~2.2 x Nyquist reaches; spikes are well below it.
MIN_THIRD_RATIO = 0.1
#: A neighbour of a spike belongs to it (a cosmic ray over two pixels) when it stands at
#: least this fraction of the spike's height above the background (a bead's core next
#: to a hot pixel does not).
PARTNER_RATIO = 0.3
#: Variance of the rounding error of an integer image, ADU^2 (uniform on [-1/2, 1/2]).
QUANTISATION_VARIANCE = 1.0 / 12.0


def pixel_noise_sd(image, *, integer: bool | None = None, max_samples: int = 250_000) -> float:
    """Robust per-pixel noise standard deviation of an image's background.

    The median absolute deviation of the noise-normalised Laplacian
    ``(4 I - N - S - E - W) / sqrt(20)`` (whose variance is the pixel variance for white
    noise and which ignores smooth backgrounds), on a subsample of rows. For integer
    images it is never below the rounding noise ``sqrt(1/12)`` ADU: a nearly constant
    integer background has a MAD of zero, but its pixels still carry the rounding
    error of the signal under them.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    integer : bool, optional
        Whether the pixel values are integers (default: read from the dtype, or from
        the values of a floating image).
    max_samples : int
        About how many pixels the median is taken on.

    Returns
    -------
    float
        Noise sd in image units, > 0.
    """
    img = np.asarray(image)
    if integer is None:
        integer = is_integer_valued(img)
    h, w = img.shape
    step = max(1, int(np.sqrt(h * w / max_samples)))
    rows = np.arange(1, h - 1, step)[:, None]
    cols = np.arange(1, w - 1, step)[None, :]
    mid = img[rows, cols].astype(np.float64)
    lap = (4 * mid - img[rows - 1, cols] - img[rows + 1, cols] - img[rows, cols - 1]
           - img[rows, cols + 1]).ravel() / np.sqrt(20.0)
    med = float(np.median(lap))
    sd = 1.4826 * float(np.median(np.abs(lap - med)))
    floor = np.sqrt(QUANTISATION_VARIANCE) if integer else 0.0
    if not np.isfinite(sd) or sd <= floor:
        sd = max(floor, sd if np.isfinite(sd) else 0.0)
    if sd <= 0:  # a noiseless floating image: any positive scale will do
        sd = max(float(np.std(lap)), 1e-12 * max(float(np.abs(mid).max()), 1.0), 1e-30)
    return sd


def is_integer_valued(image) -> bool:
    """True for integer dtypes, and for floating images whose values are all integers."""
    img = np.asarray(image)
    if img.dtype.kind in "uib":
        return True
    sample = img.ravel()[:: max(1, img.size // 100_000)]
    return bool(np.all(sample == np.round(sample)))


def find_spikes(
    image,
    *,
    noise_sd: float | None = None,
    k: float = 6.0,
    min_ratio: float = MIN_THIRD_RATIO,
    z: float = 2.0,
    integer: bool | None = None,
) -> np.ndarray:
    """Pixels narrower than the optics can form: hot pixels and cosmic rays.

    A pixel is a spike when it is a local maximum of its 3 x 3 neighbourhood, stands
    more than ``k`` noise sd above the local background ``b`` (median of the ring of
    pixels at Chebyshev distance 2), and the third brightest pixel ``t`` of its 3 x 3
    neighbourhood is below what a band-limited spot of that height reaches, by more
    than ``z`` noise sd: ``t - b < min_ratio (peak - b) - z sd``. Neighbours of a spike
    that stand above ``max(3 sd, PARTNER_RATIO (peak - b))`` belong to it (a cosmic ray
    over two pixels) and are returned too.

    For integer images the noise sd at a candidate also holds the shot noise of photon
    counts at its level: ``sd^2 = noise_sd^2 + (ring mean - image minimum)`` (one count
    per ADU, the most a photon-counting or low-gain camera shows). The background's
    robust spread alone misses the long tail of a few counts: on a confocal image of
    well under one count per pixel it takes single-photon bursts for hot pixels.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Raw image, any real dtype.
    noise_sd : float, optional
        Background noise sd (image units); default :func:`pixel_noise_sd`.
    k : float
        Height (noise sd above the local background) from which a spike is sought.
    min_ratio : float
        Smallest ratio third brightest / maximum of a band-limited spot
        (:data:`MIN_THIRD_RATIO`).
    z : float
        Margin in noise sd: a faint spot is called a spike only when it is clearly
        sharper than any optics allow.
    integer : bool, optional
        Whether the values are counts (default: :func:`is_integer_valued`).

    Returns
    -------
    ndarray of shape (S, 2), int64
        ``(row, column)`` of the spike pixels, sorted.
    """
    img = np.asarray(image)
    a = img.astype(np.float32, copy=False)
    h, w = a.shape
    if h < 5 or w < 5:
        return np.zeros((0, 2), np.int64)
    if integer is None:
        integer = is_integer_valued(img)
    sd = pixel_noise_sd(img, integer=integer) if noise_sd is None else float(noise_sd)
    # candidates: pixels well above a 7 x 7 box mean (the one full-image filter), then
    # only the local maxima of their 3 x 3 neighbourhood
    box = filter_by_rows(lambda x: ndi.uniform_filter(x, size=7, mode="nearest"), a, 4)
    box -= a
    ys, xs = np.nonzero(box < -k * sd)
    if len(ys) == 0:
        return np.zeros((0, 2), np.int64)
    d = np.arange(-2, 3)
    # mirrored about the edge pixels (not repeating them): a spike on the border row is
    # not its own neighbour
    rows = _reflect(ys[:, None, None] + d[None, :, None], h)
    cols = _reflect(xs[:, None, None] + d[None, None, :], w)
    win = a[rows, cols]
    top3 = win[:, 1:4, 1:4].reshape(len(ys), 9)
    peak = top3[:, 4] >= top3.max(axis=1)
    ys, xs, win = ys[peak], xs[peak], win[peak].astype(np.float64)
    ring = np.concatenate([win[:, 0, :], win[:, -1, :], win[:, 1:-1, 0], win[:, 1:-1, -1]],
                          axis=1)
    bg = np.median(ring, axis=1)
    local = np.full(len(ys), sd)
    if integer:  # the shot noise of counts at the local level
        local = np.sqrt(sd**2 + np.maximum(ring.mean(axis=1) - float(a.min()), 0.0))
    inner = win[:, 1:4, 1:4].reshape(len(ys), 9)
    top = np.sort(inner, axis=1)
    height = top[:, -1] - bg
    third = top[:, -3] - bg
    spike = (height > k * local) & (third < min_ratio * height - z * local)
    if not spike.any():
        return np.zeros((0, 2), np.int64)
    ys, xs, inner, bg, height = ys[spike], xs[spike], inner[spike], bg[spike], height[spike]
    local = local[spike]
    # the spike's own pixels: the maximum and neighbours far above the background
    part = (inner - bg[:, None]) > np.maximum(3 * local, PARTNER_RATIO * height)[:, None]
    part[:, 4] = True
    off = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    sel_spike, sel_pix = np.nonzero(part)
    out = np.column_stack([ys[sel_spike] + off[sel_pix, 0], xs[sel_spike] + off[sel_pix, 1]])
    inside = (out[:, 0] >= 0) & (out[:, 0] < h) & (out[:, 1] >= 0) & (out[:, 1] < w)
    return np.unique(out[inside].astype(np.int64), axis=0)


def _reflect(index: np.ndarray, n: int) -> np.ndarray:
    """Indices mirrored about the first and last pixel (-1 -> 1, n -> n - 2)."""
    index = np.abs(index)
    return np.where(index > n - 1, 2 * (n - 1) - index, index)


def inpaint_pixels(image, pixels, *, copy: bool = True) -> np.ndarray:
    """Replace pixels by the median of their unmasked 3 x 3 neighbours.

    Parameters
    ----------
    image : ndarray of shape (M, N), floating
    pixels : array_like of shape (S, 2), int
        ``(row, column)`` of the pixels to replace (e.g. :func:`find_spikes`).
    copy : bool
        False: modify ``image`` in place.

    Returns
    -------
    ndarray of shape (M, N)
    """
    out = np.array(image, copy=True) if copy else image
    pix = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
    if len(pix) == 0:
        return out
    h, w = out.shape
    masked = np.zeros(out.shape, bool)
    masked[pix[:, 0], pix[:, 1]] = True
    d = np.arange(-1, 2)
    rows = np.clip(pix[:, 0, None, None] + d[None, :, None], 0, h - 1)
    cols = np.clip(pix[:, 1, None, None] + d[None, None, :], 0, w - 1)
    vals = out[rows, cols].reshape(len(pix), 9).astype(np.float64)
    ok = ~masked[rows, cols].reshape(len(pix), 9)
    vals[~ok] = np.nan
    fill = np.nanmedian(np.where(ok.any(axis=1)[:, None], vals, 0.0), axis=1)
    # a pixel whose whole neighbourhood is masked: the median of a 5 x 5 window
    lonely = ~ok.any(axis=1)
    if lonely.any():
        d5 = np.arange(-2, 3)
        r5 = np.clip(pix[lonely, 0, None, None] + d5[None, :, None], 0, h - 1)
        c5 = np.clip(pix[lonely, 1, None, None] + d5[None, None, :], 0, w - 1)
        fill[lonely] = np.median(out[r5, c5].reshape(int(lonely.sum()), 25), axis=1)
    out[pix[:, 0], pix[:, 1]] = fill.astype(out.dtype)
    return out


def spike_mask(shape: tuple[int, int], pixels) -> np.ndarray:
    """Boolean image, True at ``pixels`` (S, 2; None: none)."""
    mask = np.zeros(shape, bool)
    if pixels is None:
        return mask
    pix = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
    if len(pix):
        mask[pix[:, 0], pix[:, 1]] = True
    return mask
