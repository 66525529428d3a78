"""The simulated camera: electrons to ADU with gain, offset and read noise, and
digitisation to an integer type (8/12/16-bit) with saturation at full scale.
"""

from __future__ import annotations

import numpy as np


def camera_adu(
    rng: np.random.Generator,
    photons: np.ndarray,
    gain: float,
    offset: float,
    read_noise: float,
) -> np.ndarray:
    """Poisson shot noise, gain, offset, Gaussian read noise: float64 ADU."""
    adu = gain * rng.poisson(photons).astype(np.float64) + offset
    adu += rng.normal(0.0, read_noise * gain, photons.shape)
    return adu


def digitise(adu: np.ndarray, dtype: np.dtype, level: float | None = None) -> np.ndarray:
    """Integer dtypes rounded and clipped to their range; everything clipped at ``level``."""
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        adu = np.clip(np.rint(adu), info.min, info.max if level is None else level)
    elif level is not None:
        adu = np.minimum(adu, level)
    return adu.astype(dtype)


def camera(
    rng: np.random.Generator,
    photons: np.ndarray,
    gain: float,
    offset: float,
    read_noise: float,
    dtype: np.dtype,
) -> np.ndarray:
    """Poisson shot noise, gain, offset, Gaussian read noise; integer dtypes rounded, clipped."""
    return digitise(camera_adu(rng, photons, gain, offset, read_noise), dtype)


def as_range(value: float | tuple[float, float], name: str) -> tuple[float, float]:
    low, high = (float(value), float(value)) if np.isscalar(value) else map(float, value)
    if not 0 <= low <= high:
        raise ValueError(f"{name} must satisfy 0 <= low <= high, got {value!r}")
    return low, high
