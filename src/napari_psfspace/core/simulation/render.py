"""Bead layout and rendering for the simulator: beads placed at a minimum separation
from each other and the border, a smooth background, and each bead's pixel-integrated PSF
added on its window.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from .aberrations import FieldAberrations
from .optics import Optics, object_pad, psf_stack


def place_beads(
    rng: np.random.Generator,
    shape: tuple[int, int],
    n_beads: int,
    min_separation: float,
    border: float,
) -> np.ndarray:
    """Dart throwing: ``n_beads`` uniform positions ``(row, col)``, pairwise >= ``min_separation``.

    Raises ValueError when the beads do not fit (packing bound) or when the
    attempt budget is exhausted.
    """
    lo = np.array([border, border], float)
    hi = np.array([shape[0] - 1 - border, shape[1] - 1 - border], float)

    def fail(placed: int) -> ValueError:
        return ValueError(
            f"could not place n_beads={n_beads} beads at least min_separation={min_separation:g} "
            f"px apart and border={border:g} px from the border of an image of shape={shape} "
            f"(placed {placed}); reduce n_beads or min_separation, or enlarge the image"
        )

    if n_beads == 0:
        return np.empty((0, 2))
    if np.any(hi < lo):
        raise fail(0)
    # Hexagonal packing of disks of diameter min_separation bounds the count.
    extent = hi - lo + min_separation
    if min_separation > 0 and n_beads > extent.prod() / (np.sqrt(3) / 2 * min_separation**2):
        raise fail(0)

    cell = max(min_separation / np.sqrt(2), 1e-9)  # at most one bead per cell
    owner = -np.ones((np.ceil((hi - lo) / cell) + 1).astype(int), int)
    positions = np.empty((n_beads, 2))
    placed, attempts, max_attempts = 0, 0, 200 * n_beads + 20_000
    while placed < n_beads:
        if attempts >= max_attempts:
            raise fail(placed)
        candidates = rng.uniform(lo, hi, size=(1024, 2))
        attempts += len(candidates)
        for pos in candidates:
            cy, cx = ((pos - lo) // cell).astype(int)
            near = owner[max(cy - 2, 0) : cy + 3, max(cx - 2, 0) : cx + 3]
            near = near[near >= 0]
            if (
                near.size
                and np.min(np.sum((positions[near] - pos) ** 2, axis=1)) < min_separation**2
            ):
                continue
            positions[placed] = pos
            owner[cy, cx] = placed
            placed += 1
            if placed == n_beads:
                break
    return positions


def smooth_background(
    rng: np.random.Generator, shape: tuple[int, int], low: float, high: float
) -> np.ndarray:
    """Gaussian random field (white noise smoothed with sigma ``min(shape)/6``) in [low, high]."""
    noise = rng.standard_normal(shape)
    if high == low:
        return np.full(shape, low, np.float32)
    sigma = min(shape) / 6.0
    ky, kx = sfft.fftfreq(shape[0]), sfft.rfftfreq(shape[1])
    kernel = np.exp(-2.0 * (np.pi * sigma) ** 2 * (ky[:, None] ** 2 + kx[None, :] ** 2))
    field_ = sfft.irfft2(sfft.rfft2(noise, workers=-1) * kernel, s=shape, workers=-1)
    field_ = (field_ - field_.min()) / max(np.ptp(field_), np.finfo(float).tiny)
    return (low + (high - low) * field_).astype(np.float32)


def render_beads(
    image: np.ndarray,
    positions: np.ndarray,
    amplitudes: np.ndarray,
    aberrations: FieldAberrations,
    optics: Optics,
    radius: int,
    diameters: np.ndarray | None = None,
    drift: tuple[float, float] | None = None,
) -> np.ndarray:
    """Add ``amplitude * PSF`` of each bead into ``image`` (in place); return each PSF's peak value.

    Each PSF uses the Zernike coefficients at the bead's own position and its
    sub-pixel offset; windows of side ``2 radius + 1`` are clipped at the border.
    ``diameters`` (µm, per bead) and ``drift`` (pixels) are passed to
    :func:`psf_stack`; the window radius then grows by :func:`object_pad`.
    """
    radius += object_pad(optics, diameters, drift)
    size = 2 * radius + 1
    centres = np.rint(positions).astype(int)
    offsets = positions - centres
    coefs = aberrations.coefficient_matrix(positions[:, 0], positions[:, 1], image.shape)
    peaks = np.empty(len(positions))
    chunk = 64  # bounds the memory of the PSF stack
    for start in range(0, len(positions), chunk):
        sl = slice(start, start + chunk)
        if diameters is None and drift is None:
            psfs = psf_stack(aberrations.noll_indices, coefs[sl], offsets[sl], optics, size)
        else:
            psfs = psf_stack(
                aberrations.noll_indices,
                coefs[sl],
                offsets[sl],
                optics,
                size,
                diameters=None if diameters is None else diameters[sl],
                drift=drift,
            )
        for k, psf in enumerate(psfs, start):
            peaks[k] = psf.max()
            (y0, x0), (y1, x1) = centres[k] - radius, centres[k] + radius + 1
            sy, sx = max(y0, 0), max(x0, 0)
            ey, ex = min(y1, image.shape[0]), min(x1, image.shape[1])
            image[sy:ey, sx:ex] += amplitudes[k] * psf[sy - y0 : ey - y0, sx - x0 : ex - x0]
    return peaks


def spawn(rng: np.random.Generator, n: int) -> list[np.random.Generator]:
    """``n`` independent child generators of ``rng`` without drawing from its stream."""
    try:
        return rng.spawn(n)
    except (AttributeError, TypeError, ValueError):  # bit generator without a seed sequence
        return [np.random.default_rng(s) for s in rng.integers(0, 2**63, size=n)]
