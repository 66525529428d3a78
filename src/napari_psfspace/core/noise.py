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

from ._validate import as_image


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
    """

    gain: float
    intercept: float
    offset: float | None = None
    read_noise: float | None = None
    mean_range: tuple[float, float] = (0.0, 0.0)
    n_pixels: int = 0

    def variance(self, mean) -> np.ndarray:
        """Expected variance (ADU^2) of pixels of expected value ``mean`` (ADU).

        Floored at a small positive value so that chi-square weights stay finite.
        """
        v = self.gain * np.asarray(mean, dtype=np.float64) + self.intercept
        floor = max(1e-6, 0.05 * max(self.gain, 0) ** 2)
        return np.maximum(v, floor)

    def to_dict(self) -> dict:
        """JSON-ready dictionary."""
        d = asdict(self)
        d["mean_range"] = list(self.mean_range)
        return d

    @classmethod
    def from_camera(cls, gain: float, offset: float, read_noise: float) -> NoiseModel:
        """The model of a camera of known gain (ADU/e-), offset (ADU), read noise (e-)."""
        if gain <= 0 or read_noise < 0:
            raise ValueError(f"`gain` must be > 0 and `read_noise` >= 0, got {gain}, "
                             f"{read_noise}.")
        return cls(gain, gain**2 * read_noise**2 - gain * offset, offset, read_noise)


def _structure_mask(img: np.ndarray, sigma: float, k: float) -> np.ndarray:
    """Pixels near structure: |LoG| above ``k`` robust sd, dilated."""
    log = ndi.gaussian_laplace(img, sigma)
    med = np.median(log[::4, ::4])
    mad = 1.4826 * np.median(np.abs(log[::4, ::4] - med)) or float(log.std()) or 1.0
    struct = np.abs(log - med) > k * mad
    return ndi.binary_dilation(struct, iterations=int(np.ceil(3 * sigma)))


def estimate_noise(
    image,
    *,
    mask=None,
    offset: float | None = None,
    n_bins: int = 16,
    saturation: float | None = None,
) -> NoiseModel:
    """Estimate ``var = a * mean + b`` from the structure-free pixels of one image.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Raw camera image in ADU (not background-subtracted, not rescaled).
    mask : array_like of shape (M, N), bool, optional
        True where pixels must not be used (e.g. around beads). Structure found by a
        Laplacian-of-Gaussian test is excluded in any case.
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

    Raises
    ------
    ValueError
        When fewer than 1000 usable pixels remain, or the fitted slope is not positive
        (no Poisson signature: e.g. a rescaled or denoised image).
    """
    raw = np.asarray(image)
    img = as_image(raw, dtype=np.float64)
    if saturation is None and raw.dtype.kind in "ui":
        saturation = float(np.iinfo(raw.dtype).max)
    lap = (4 * img[1:-1, 1:-1] - img[:-2, 1:-1] - img[2:, 1:-1] - img[1:-1, :-2]
           - img[1:-1, 2:]) / np.sqrt(20.0)
    local = ndi.uniform_filter(img, 5)[1:-1, 1:-1]
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
    use = ~bad[1:-1, 1:-1]
    if np.count_nonzero(use) < 1000:
        frac = float(np.mean(clipped))
        why = (f" {100 * frac:.0f} % of the pixels sit at the image's minimum "
               f"({img.min():g}), i.e. the background is clipped." if frac > 0.2 else "")
        raise ValueError(
            f"Too few structure-free pixels to estimate the noise: {np.count_nonzero(use)}, "
            f"need at least 1000.{why} Pass the camera's gain, offset and read noise instead."
        )
    mu, e = local[use], lap[use]
    edges = np.unique(np.quantile(mu, np.linspace(0, 1, n_bins + 1)))
    which = np.clip(np.searchsorted(edges, mu, side="right") - 1, 0, len(edges) - 2)
    means, variances, weights = [], [], []
    for b in range(len(edges) - 1):
        sel = which == b
        if np.count_nonzero(sel) < 50:
            continue
        eb = e[sel]
        mad = np.median(np.abs(eb - np.median(eb)))
        v = (1.4826 * mad) ** 2
        means.append(float(np.mean(mu[sel])))
        variances.append(v)
        weights.append(np.count_nonzero(sel) / max(v, 1e-12) ** 2)
    means, variances, w = np.array(means), np.array(variances), np.array(weights)
    if len(means) >= 3 and np.ptp(means) > 1e-9:
        a, b = np.polyfit(means, variances, 1, w=np.sqrt(w))
    else:
        a, b = float("nan"), float(np.mean(variances))
    if not np.isfinite(a) or a <= 0:
        raise ValueError(
            f"No Poisson signature in `image`: the noise variance does not grow with the "
            f"mean (fitted slope {a:.3g} over means {means.min():.4g}-{means.max():.4g}). "
            "The image may be rescaled, denoised or too uniform: pass the camera's gain, "
            "offset and read noise instead."
        )
    read = None
    if offset is not None:
        r2 = (b + a * offset) / a**2
        read = float(np.sqrt(max(r2, 0.0)))
    return NoiseModel(float(a), float(b), offset, read, (float(means.min()),
                      float(means.max())), int(mu.size))
