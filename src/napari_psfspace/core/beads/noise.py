"""Poisson-Gaussian noise model of a camera image, estimated from the image itself.

A camera pixel of expected value ``mu`` (ADU) has variance ``a * mu + b`` with
``a = gain`` (ADU per photo-electron) and ``b = gain^2 sigma_read^2 - gain * offset``
(photon transfer). From a single image, pairs (local mean, local noise variance) are
collected where the image holds no structure: the local noise comes from a
noise-normalised Laplacian ``(4 I - N - S - E - W) / sqrt(20)``, whose variance is the
pixel variance for white noise and which ignores smooth backgrounds. Pixels are binned
by local mean; a robust (MAD) variance per bin and a weighted line fit give ``a`` and
``b``. The offset and read noise are separately identifiable only when the offset is
known (``offset=``, e.g. from a dark frame or the camera sheet).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage as ndi

from ..common.errors import PsfSpaceError
from ..common.progress import check_halt
from ..common.validate import as_array, as_image, check_camera
from .spikes import QUANTISATION_VARIANCE, is_integer_valued


@dataclass(frozen=True)
class NoiseModel:
    """Pixel variance ``a * mean + b`` (ADU^2) of a Poisson-Gaussian camera.

    Attributes
    ----------
    gain : float
        ``a``: ADU per photo-electron (the slope of variance against mean).
    intercept : float
        ``b`` in ADU^2.
    offset : float or None
        Camera offset (ADU), when known.
    read_noise : float or None
        Read noise in electrons rms, when the offset is known.
    mean_range : tuple of float
        Range of local means (ADU) the fit was made on: outside it the model is an
        extrapolation.
    n_pixels : int
        Number of pixels used.
    kind : str
        How it was obtained: "camera" (values given), "photon transfer", or a fallback
        ("constant", "unit-gain Poisson"; see :func:`noise_model`).
    note : str
        Why a fallback was used, and what it means for the chi-square.
    checks : dict or None
        Photon transfer's fit figures (levels, slope z, reduced chi-square).
    min_variance : float
        No pixel's variance is below it: 1/12 ADU^2 (the rounding) for integer images.
    """

    gain: float
    intercept: float
    offset: float | None = None
    read_noise: float | None = None
    mean_range: tuple[float, float] = (0.0, 0.0)
    n_pixels: int = 0
    kind: str = "camera"
    note: str = ""
    checks: dict | None = None
    min_variance: float = 0.0

    def variance(self, mean) -> np.ndarray:
        """Expected variance (ADU^2) of pixels of expected value ``mean`` (ADU).

        Floored at a small positive value so that chi-square weights stay finite.
        """
        v = self.gain * np.asarray(mean, dtype=np.float64) + self.intercept
        floor = max(1e-6, 0.05 * max(self.gain, 0) ** 2, self.min_variance)
        return np.maximum(v, floor)

    def to_dict(self) -> dict:
        """JSON-ready dictionary."""
        d = asdict(self)
        d["mean_range"] = list(self.mean_range)
        if d["checks"] is None:
            d.pop("checks")
        return d

    @property
    def description(self) -> str:
        """One line: the model and how it was obtained."""
        if self.kind == "constant":
            return f"constant variance {self.intercept:.4g} ADU² (fallback: {self.note})"
        sign = "+" if self.intercept >= 0 else "-"
        line = (f"variance = {self.gain:.4g} x mean {sign} {abs(self.intercept):.4g} ADU² "
                f"(gain {self.gain:.4g} ADU/e-)")
        if self.kind == "unit-gain Poisson":
            return line + f" (fallback: {self.note})"
        return line + f", {self.kind}"

    @classmethod
    def from_camera(cls, gain: float, offset: float, read_noise: float) -> NoiseModel:
        """The model of a camera of known gain (ADU/e-), offset (ADU), read noise (e-)."""
        gain, offset, read_noise, _ = check_camera(gain, offset, read_noise)
        return cls(gain, gain**2 * read_noise**2 - gain * offset, offset, read_noise)


def _structure_mask(img: np.ndarray, sigma: float, k: float,
                    scales: tuple[float, ...] = (1.0, 2.0)) -> np.ndarray:
    """Pixels near structure: |LoG| above ``k`` robust sd at scale ``sigma`` or at the
    larger ``scales`` (multiples of it: the faint, wide wings of a bright bead curve
    too gently to show at the smaller one), dilated by 3 scales."""
    check_halt()
    out = np.zeros(img.shape, bool)
    for f in scales:
        s = sigma * f
        log = ndi.gaussian_laplace(img, s)
        med = np.median(log[::4, ::4])
        mad = 1.4826 * np.median(np.abs(log[::4, ::4] - med)) or float(log.std()) or 1.0
        struct = np.abs(log - med) > k * mad
        out |= ndi.binary_dilation(struct, iterations=int(np.ceil(3 * s)))
    return out


class NoiseModelError(PsfSpaceError):
    """Photon transfer failed one of its checks (the message says which and why)."""


#: Physically plausible camera gains, ADU per photo-electron: from an 8-bit export of a
#: 16-bit camera (~1/256 of a unit gain) to an EMCCD at full electron multiplication.
GAIN_BOUNDS = (1e-3, 1e3)
#: The Poisson slope must stand this many standard errors above zero.
MIN_SLOPE_Z = 3.0
#: Largest reduced chi-square of the bin variances about the fitted line; beyond it the
#: variance does not follow ``a mean + b`` (structure, fixed pattern, a processed image).
MAX_FIT_CHI2 = 25.0
#: Noise-normalised Laplacian samples farther than this many robust sd from their
#: median are left out of a bin's variance (structure the mask missed, hot pixels).
CLIP_SD = 5.0
#: Side (pixels) of the box whose mean (over its structure-free pixels) is a pixel's
#: level. Wide, so that the level is not the pixel's own noise: binned by a noisy level,
#: the variance-vs-level slope is diluted (a narrow box under-estimates the gain at a few
#: photons, ``bench/bench_camera.py``); what dilution is left is corrected.
LEVEL_WINDOW = 31
#: Photon transfer needs at least this share of the spread of the measured levels to be
#: true variation of the background (not the levels' own noise).
MIN_LEVEL_SHARE = 0.5
#: For integer images, the noise variance must reach this many times the rounding
#: variance 1/12 ADU^2 at every level: below it the variance of rounded values swings with
#: the level's distance to the nearest integer, which photon transfer would read as a
#: slope (on 8-bit scenes with a noise sd under 0.5 ADU, ``bench/bench_camera.py``).
MIN_ROUNDING_RATIO = 4.0
#: Variance of a MAD-based variance estimate from n Gaussian samples is about
#: ``MAD_VARIANCE_FACTOR v^2 / n`` (the MAD's efficiency is 37 %); the Laplacian samples
#: are correlated (each pixel enters five), which :data:`SAMPLE_CORRELATION` accounts for.
MAD_VARIANCE_FACTOR = 5.4
SAMPLE_CORRELATION = 1.2


def _noise_laplacian(img: np.ndarray, integer: bool) -> np.ndarray:
    """Noise-normalised Laplacian ``(4 I - N - S - E - W) / sqrt(20)``, shape (M-2, N-2).

    For integer images each pixel is first dithered by a uniform ``[-1/2, 1/2)`` value
    (seeded): the Laplacian of rounded values takes few distinct values, and their
    median absolute deviation is too coarse to follow the variance from bin to bin (it
    can take the same value in every bin: a slope of 0). The dither's variance
    is removed again in :func:`_robust_variance`.
    """
    check_halt()
    if integer:
        dither = np.random.default_rng(0).uniform(-0.5, 0.5, img.shape)
        img = img + dither
    return (4 * img[1:-1, 1:-1] - img[:-2, 1:-1] - img[2:, 1:-1] - img[1:-1, :-2]
            - img[1:-1, 2:]) / np.sqrt(20.0)


def _robust_variance(e: np.ndarray, integer: bool) -> float:
    """Variance of noise-normalised Laplacian samples, less the dither's 1/12 for integer
    images (see :func:`_noise_laplacian`).

    The plain variance of the samples within :data:`CLIP_SD` robust sd (MAD) of their
    median: the MAD alone is biased low for the skewed, heavy-tailed noise of a few photons
    (``bench/bench_camera.py``), the clipping keeps
    what the structure mask missed from deciding the variance.
    """
    med = float(np.median(e))
    sd = 1.4826 * float(np.median(np.abs(e - med)))
    keep = np.abs(e - med) <= CLIP_SD * sd if sd > 0 else np.ones(e.shape, bool)
    v = float(np.var(e[keep])) if keep.sum() > 1 else sd**2
    return v - QUANTISATION_VARIANCE if integer else v


def _photon_transfer_points(img, use, local, lap, n_bins, integer):
    """Binned (mean, robust variance, n) of the structure-free pixels."""
    check_halt()
    mu, e = local[use], lap[use]
    edges = np.unique(np.quantile(mu, np.linspace(0, 1, n_bins + 1)))
    which = np.clip(np.searchsorted(edges, mu, side="right") - 1, 0, len(edges) - 2)
    floor = QUANTISATION_VARIANCE if integer else 0.0
    means, variances, counts = [], [], []
    for b in range(len(edges) - 1):
        sel = which == b
        n = int(np.count_nonzero(sel))
        if n < 50:
            continue
        means.append(float(np.mean(mu[sel])))
        variances.append(max(_robust_variance(e[sel], integer), floor))
        counts.append(n)
    return np.array(means), np.array(variances), np.array(counts), mu.size


def estimate_noise(
    image,
    *,
    mask=None,
    offset: float | None = None,
    n_bins: int = 16,
    saturation: float | None = None,
) -> NoiseModel:
    """Estimate ``var = a * mean + b`` from the structure-free pixels of one image.

    Photon transfer checks its own fit and raises :class:`NoiseModelError` (a
    ValueError) naming the check that failed, rather than return a model it cannot
    stand behind:

    * the slope ``a`` (the gain) must be positive and stand :data:`MIN_SLOPE_Z`
      standard errors above zero: the local means must span enough distinct levels
      for the shot noise to show (a flat background does not);
    * at least :data:`MIN_LEVEL_SHARE` of the spread of the levels (box means) must be
      true variation, not their own noise; the slope is corrected for the dilution
      that noise causes (errors in variables);
    * the gain must lie within :data:`GAIN_BOUNDS` ADU per photo-electron;
    * for integer images, the noise must stand above the rounding (variance at least
      :data:`MIN_ROUNDING_RATIO` / 12 ADU^2 at every level);
    * the line must fit the binned variances (reduced chi-square at most
      :data:`MAX_FIT_CHI2` under their sampling error);
    * the variance must be positive over the measured range.

    For integer images no bin variance is taken below the rounding noise, 1/12 ADU^2:
    the robust spread of a nearly constant integer background is zero, its noise is not.
    :func:`noise_model` falls back to a stated simpler model when a check fails.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Raw camera image in ADU (not background-subtracted, not rescaled).
    mask : array_like of shape (M, N), bool, optional
        True where pixels must not be used (e.g. around beads, hot pixels). Structure
        found by a Laplacian-of-Gaussian test is excluded in any case.
    offset : float, optional
        Known camera offset (ADU); gives the read noise in electrons.
    n_bins : int
        Number of local-mean bins (quantiles) of the fit.
    saturation : float, optional
        Pixels at or above it are excluded (default: the dtype maximum of integer
        images). Pixels at the dtype minimum (clipped) are excluded too.

    Returns
    -------
    NoiseModel
        ``kind`` "photon transfer", with the fit's checks in ``checks``.

    Raises
    ------
    NoiseModelError
        Too few usable pixels (e.g. a clipped background), or a failed check.
    """
    raw = np.asarray(as_array(image, "image"))
    img = as_image(raw, dtype=np.float64)
    integer = is_integer_valued(raw)
    if saturation is None and raw.dtype.kind in "ui":
        saturation = float(np.iinfo(raw.dtype).max)
    lap = _noise_laplacian(img, integer)
    local, n_level, use = _usable_pixels(mask, saturation, img)
    means, variances, counts, n_pix = _photon_transfer_points(img, use, local, lap, n_bins,
                                                              integer)
    floor_v = QUANTISATION_VARIANCE if integer else 1e-12
    checks = {"n_levels": int(len(means)),
              "mean_range": [float(means.min()), float(means.max())] if len(means) else []}
    if len(means) < 3 or np.ptp(means) <= 1e-9:
        levels = np.unique(local[use])
        span = (f"{levels.min():.4g}-{levels.max():.4g} ADU" if len(levels) > 1
                else f"all at {levels[0]:.4g} ADU")
        raise NoiseModelError(
            f"No Poisson signature in `image`: the structure-free pixels' local levels "
            f"({span}) fill {len(means)} bin(s) of at least 50 pixels, need 3 distinct "
            "ones: the slope of variance against mean (the gain) cannot be measured. "
            "Pass the camera's gain, offset and read noise instead.")
    variances, means, b, a, chi2, z, kept = _fit_line(
            local, n_level, use, counts, variances, means, floor_v, checks)
    _check_fit(integer, variances, means, b, a, chi2, z, kept)
    read = None
    if offset is not None:
        r2 = (b + a * offset) / a**2
        read = float(np.sqrt(max(r2, 0.0)))
    return NoiseModel(a, b, offset, read, (float(means.min()), float(means.max())),
                      int(n_pix), kind="photon transfer", checks=checks, min_variance=floor_v)


def _usable_pixels(mask, saturation, img):
    """The structure-free pixels (masked, clipped and saturated ones left out, with a
    margin), each one's level and the pixels behind it; one clear line where too few are
    left."""
    bad = _structure_mask(img, 2.0, 4.0)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != img.shape:
            raise ValueError(f"`mask` must have the image's shape {img.shape}, got {m.shape}.")
        bad |= m
    clipped = img <= img.min()
    if saturation is not None:
        clipped |= img >= saturation
    bad |= ndi.binary_dilation(clipped, iterations=2)
    # a pixel's level: the mean of the structure-free pixels of a wide box around it (the
    # wings of a nearby bead must not raise the level of a pixel whose noise they spare)
    free = (~bad).astype(np.float64)
    share = ndi.uniform_filter(free, LEVEL_WINDOW)
    local = (ndi.uniform_filter(img * free, LEVEL_WINDOW) / np.maximum(share, 1e-12))[1:-1, 1:-1]
    n_level = (share * LEVEL_WINDOW**2)[1:-1, 1:-1]  # pixels behind each level
    use = ~bad[1:-1, 1:-1]
    if np.count_nonzero(use) < 1000:
        frac = float(np.mean(clipped))
        why = (f" {100 * frac:.0f} % of the pixels sit at the image's minimum "
               f"({img.min():g}): the background is clipped, or a few counts." if frac > 0.2
               else "")
        raise NoiseModelError(
            f"Too few structure-free pixels to estimate the noise: {np.count_nonzero(use)}, "
            f"need at least 1000.{why} Pass the camera's gain, offset and read noise instead."
        )
    return local, n_level, use


def _fit_line(local, n_level, use, counts, variances, means, floor_v, checks):
    """The line of variance against level, corrected for the levels' own noise: the bins
    kept, the intercept and gain, the fit's reduced chi-square, the slope's z and the share
    of the levels' spread that is true variation; the fit's checks recorded."""
    # a bin of pixels without any noise (a constant region a correction left) has no
    # sampling variance to weigh it by: it says nothing of the slope
    noisy = np.isfinite(variances) & (variances > 0) & np.isfinite(means)
    if np.count_nonzero(noisy) < 3:
        raise NoiseModelError(
            f"No Poisson signature in `image`: {np.count_nonzero(noisy)} of {len(means)} "
            "levels of the structure-free pixels show any noise (the rest are constant), "
            "need 3. Pass the camera's gain, offset and read noise instead.")
    means, variances, counts = means[noisy], variances[noisy], counts[noisy]
    # weighted least squares with the bins' sampling variance; the slope's standard
    # error is scaled up by the fit's reduced chi-square when that exceeds 1
    sd_v = np.sqrt(MAD_VARIANCE_FACTOR * SAMPLE_CORRELATION / counts) * variances
    design = np.column_stack([means, np.ones_like(means)]) / sd_v[:, None]
    coef, *_ = np.linalg.lstsq(design, variances / sd_v, rcond=None)
    a, b = (float(c) for c in coef)
    resid = (variances - (a * means + b)) / sd_v
    dof = max(len(means) - 2, 1)
    chi2 = float(resid @ resid) / dof
    cov = np.linalg.pinv(design.T @ design) * max(chi2, 1.0)
    se_a = float(np.sqrt(cov[0, 0]))
    z = a / se_a if se_a > 0 else np.inf
    # the levels are box means, noisy themselves: binned by a noisy level the slope is
    # diluted by the share of the levels' spread that is true variation (errors in
    # variables); the noise of a level is the pixels' variance over their count
    mu = local[use]
    level_var = float(np.var(mu))
    level_noise = float(np.mean(np.maximum(a * mu + b, floor_v) / n_level[use]))
    kept = 1.0 - level_noise / level_var if level_var > 0 else 0.0
    if kept >= MIN_LEVEL_SHARE:
        centre = float(np.mean(mu))
        b -= (a / kept - a) * centre
        a, se_a = a / kept, se_a / kept
    checks.update(slope_z=float(z), fit_chi2=chi2, gain=a, intercept=b,
                  level_spread_kept=float(kept),
                  gain_relative_error=float(se_a / a) if a > 0 else None,
                  variance_range=[float(variances.min()), float(variances.max())])
    return variances, means, b, a, chi2, z, kept


def _check_fit(integer, variances, means, b, a, chi2, z, kept):
    """One clear line where the fit does not measure a gain: no Poisson signature, too
    little spread of the levels, noise below the rounding, an implausible gain, a variance
    off the line or not positive."""
    problem = None
    if not np.isfinite(a) or a <= 0 or z < MIN_SLOPE_Z:
        problem = (f"No Poisson signature in `image`: the noise variance does not grow "
                   f"measurably with the mean (fitted slope {a:.3g} ADU/e-, {z:.2g} standard "
                   f"errors from zero, need {MIN_SLOPE_Z:g}, over means "
                   f"{means.min():.4g}-{means.max():.4g} ADU). The background may be too "
                   "uniform, or the image rescaled or denoised")
    elif kept < MIN_LEVEL_SHARE:
        problem = (f"The background's level varies too little across the image: "
                   f"{100 * (1 - kept):.0f} % of the spread of the measured levels "
                   f"({means.min():.4g}-{means.max():.4g} ADU) is their own noise, so the "
                   "slope of variance against level (the gain) cannot be measured")
    elif integer and variances.min() < MIN_ROUNDING_RATIO * QUANTISATION_VARIANCE:
        problem = (f"The noise at the background ({np.sqrt(variances.min()):.2g} ADU sd) is "
                   f"not above the rounding of the integer pixel values (sd "
                   f"{np.sqrt(QUANTISATION_VARIANCE):.2g} ADU): the shot noise cannot be "
                   "measured (an image exported at a low gain, e.g. rescaled to 8 bits)")
    elif not GAIN_BOUNDS[0] <= a <= GAIN_BOUNDS[1]:
        problem = (f"The fitted gain {a:.3g} ADU/e- is outside the physically plausible "
                   f"range {GAIN_BOUNDS[0]:g}-{GAIN_BOUNDS[1]:g} ADU/e-")
    elif chi2 > MAX_FIT_CHI2:
        problem = (f"The variance does not follow a line in the mean (reduced chi-square "
                   f"{chi2:.3g} about the fit, at most {MAX_FIT_CHI2:g}): the background "
                   "holds structure or a pattern the noise model cannot describe")
    elif a * means.min() + b <= 0:
        problem = (f"The fitted variance is not positive at the lowest level "
                   f"({a:.3g} x {means.min():.4g} + {b:.3g} ADU^2)")
    if problem is not None:
        raise NoiseModelError(problem + ". Pass the camera's gain, offset and read noise "
                              "instead.")


def background_variance(image, *, mask=None) -> tuple[float, float, float]:
    """Robust level, noise variance and clipped fraction of an image's background.

    Returns
    -------
    level : float
        Median of the image (ADU).
    variance : float
        Pixel noise variance from the noise-normalised Laplacian's MAD over the
        structure-free pixels (at least 1/12 ADU^2 for integer images), ADU^2.
    clipped : float
        Fraction of the pixels at the image's minimum.
    """
    raw = np.asarray(as_array(image, "image"))
    img = as_image(raw, dtype=np.float64)
    integer = is_integer_valued(raw)
    level = float(np.median(img))
    bad = _structure_mask(img, 2.0, 4.0)
    if mask is not None:
        bad |= np.asarray(mask, dtype=bool)
    lap = _noise_laplacian(img, integer)
    e = lap[~bad[1:-1, 1:-1]]
    if e.size < 100:
        e = lap.ravel()
    var = _robust_variance(e, integer)
    floor = QUANTISATION_VARIANCE if integer else 1e-12
    clipped = float(np.mean(img <= img.min()))
    return level, max(var, floor), clipped


def noise_model(
    image,
    *,
    mask=None,
    gain: float | None = None,
    offset: float | None = None,
    read_noise: float | None = None,
) -> NoiseModel:
    """The noise model of an image: the camera's values, photon transfer, or a fallback.

    In order: the camera's ``gain``, ``offset`` and ``read_noise`` when given (all three);
    else photon transfer (:func:`estimate_noise`) when its checks pass; else a stated
    simpler model, with the reason in ``note``:

    * ``kind="constant"``: one variance for every pixel, the background's (its robust
      spread, at least 1/12 ADU^2 for integers). The shot noise of bright bead cores is
      not modelled, so a chi-square on them is overstated: indicative only. The
      held-out shape error does not depend on it.
    * ``kind="unit-gain Poisson"``, when the background is clipped (at least 20 % of the
      pixels at the image's minimum, so its spread cannot be measured): variance = the
      background's measured variance + the mean above the image's minimum (ADU =
      counts above the clipping level), as for a photon-counting detector.

    Returns
    -------
    NoiseModel
    """
    if gain is not None:
        as_image(image)  # the other branches read it through the same validator
        if offset is None or read_noise is None:
            raise ValueError("Give the camera's `gain`, `offset` and `read_noise` together "
                             f"(got gain={gain}, offset={offset}, read_noise={read_noise}).")
        return NoiseModel.from_camera(gain, offset, read_noise)
    try:
        return estimate_noise(image, offset=offset, mask=mask)
    except NoiseModelError as exc:
        why = str(exc).replace(" Pass the camera's gain, offset and read noise instead.", "")
    level, var, clipped = background_variance(image, mask=mask)
    floor = QUANTISATION_VARIANCE if is_integer_valued(image) else 0.0
    if clipped >= 0.2:
        low = float(np.min(image))  # the clipping level: no count below it
        return NoiseModel(1.0, var - low, offset, None, (level, level), 0,
                          kind="unit-gain Poisson", min_variance=floor,
                          note=f"photon transfer not possible ({why}); "
                               f"{100 * clipped:.0f} % of the pixels sit at the image's "
                               "minimum (a clipped background, or a few photon counts): a "
                               "photon-counting detector (1 ADU per count above the minimum) "
                               "is assumed, chi-square indicative only")
    return NoiseModel(0.0, var, offset, None, (level, level), 0, kind="constant",
                      min_variance=floor,
                      note=f"photon transfer not possible ({why}); one variance, "
                           f"{var:.3g} ADU^2, measured on the background, for every pixel: "
                           "the shot noise of bright bead cores is not modelled, so their "
                           "chi-square is overstated (indicative only)")
