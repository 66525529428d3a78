"""Optics of the simulator: the PSF of a pupil with Zernike aberrations, pixel-integrated.

Model (eq. (6) of Debarnot, Escande, Mangeat & Weiss, "Learning low-dimensional
models of microscopes", section 3.1.1): the PSF at field position ``z`` is

.. math:: h_z = |\\mathcal{F}(P \\exp(2 i \\pi W_z))|^2, \\qquad
          W_z = \\sum_j c_j(z) Z_j,

with ``P`` the indicator of the pupil disk of radius ``NA / λ`` (cycles/µm),
``Z_j`` the rms-normalised Noll Zernike polynomials (:mod:`.zernike`) and
``c_j(z)`` smooth low-degree polynomials of the field position
(:class:`FieldAberrations`).

Numerics (:func:`psf_stack`): the amplitude is the matrix Fourier transform
of the finely sampled pupil (sub-pixel shift as a phase ramp) evaluated on a
window of spacing ``p / q`` (``p`` the camera pixel, ``q`` such that the
intensity is Nyquist sampled); the intensity is normalised to unit integral
over the plane (Parseval on the pupil), Fourier transformed, multiplied by the
transfer function of the square pixel (``sinc(p kx) sinc(p ky)``, exact pixel
integration) and sampled at the pixel centres.

Units: lengths in micrometres, spatial frequencies in cycles/µm, wavefront
coefficients in waves rms, image coordinates in pixels ``(row, col)`` with
pixel centres at integers.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from math import ceil

import numpy as np
from scipy import fft as sfft

from ..beads.sphere import sphere_transfer
from ..common.validate import check_memory
from .aberrations import FieldAberrations
from .zernike import zernike

#: Largest numerical aperture accepted (refractive index of immersion oil).
MAX_NA = 1.52
#: Default fraction of the PSF energy inside the disk of radius ``psf_radius``.
#: The pixel-integrated Airy pattern of the default optics (NA 1.3, 0.6 µm,
#: 65 nm pixels) already needs r = 7 px for 90 %, 11 px for 95 % and 16 px for
#: 97 % (its energy tail decays as 1/r), so 97 % would give radii of 25-35 px
#: for the presets; 90 % keeps the estimator's windows and bead spacing compact.
PSF_ENERGY_FRACTION = 0.90
#: Beads are rendered on windows of radius ``RENDER_RADIUS_FACTOR * psf_radius``.
RENDER_RADIUS_FACTOR = 3

_MIN_PERIOD_LAMBDA_NA = 64  # amplitude period (1 / pupil bin) in units of λ/NA, at least
_WINDOW_MARGIN_PX = 8  # intensity window beyond the output window, each side, pixels
_BATCH_ELEMENTS = 1 << 21  # complex samples per batch (~32 MiB)


# ---------------------------------------------------------------------------
# Optics and field-dependent aberrations
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Optics:
    """Imaging optics of a widefield fluorescence microscope.

    Parameters
    ----------
    na : float
        Numerical aperture, ``0 < na < 1.52``.
    wavelength : float
        Emission wavelength in micrometres.
    pixel_size : float
        Camera pixel size in object space, micrometres.
    """

    na: float = 1.3
    wavelength: float = 0.6
    pixel_size: float = 0.065

    def __post_init__(self) -> None:
        for name in ("na", "wavelength", "pixel_size"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"Optics.{name} must be positive and finite, got {value!r}")
        if self.na >= MAX_NA:
            raise ValueError(f"Optics.na must be < {MAX_NA} (immersion index), got {self.na!r}")

    @property
    def cutoff(self) -> float:
        """Pupil radius ``NA / λ`` in cycles/µm (half the incoherent cutoff)."""
        return self.na / self.wavelength

    @property
    def oversampling(self) -> int:
        """Smallest ``q`` such that ``pixel_size / q <= 0.9 λ / (4 NA)`` (intensity Nyquist)."""
        return max(1, ceil(self.pixel_size / (0.9 * self.wavelength / (4.0 * self.na)) - 1e-9))


# ---------------------------------------------------------------------------
# PSF engine
# ---------------------------------------------------------------------------


@lru_cache(maxsize=16)
def _unit_disk_gradients(noll: tuple[int, ...], n: int = 41) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of ``Z_j`` sampled on the unit disk: two arrays (len(noll), P)."""
    t = np.linspace(-1.0, 1.0, n)
    yy, xx = np.meshgrid(t, t, indexing="ij")
    rho, theta = np.hypot(yy, xx), np.arctan2(yy, xx)
    inside = rho <= 1.0
    gy = np.empty((len(noll), int(inside.sum())))
    gx = np.empty_like(gy)
    for i, j in enumerate(noll):
        dzy, dzx = np.gradient(zernike(j, rho, theta), t, t)
        gy[i], gx[i] = dzy[inside], dzx[inside]
    return gy, gx


def _blur_radius(noll: tuple[int, ...], coefs: np.ndarray, optics: Optics) -> np.ndarray:
    """Geometric-optics extent of the PSFs, in pixels (ray aberration + 2 λ/NA).

    A wavefront ``W(ρ)`` in waves deflects rays by ``(λ / NA) ∇_ρ W`` (µm) in
    the object plane; the maximum over the pupil bounds the PSF support.
    """
    coefs = np.atleast_2d(coefs)
    slope = np.zeros(coefs.shape[0])
    if noll:
        gy, gx = _unit_disk_gradients(noll)
        slope = np.hypot(coefs @ gy, coefs @ gx).max(axis=1)
    return (slope + 2.0) * optics.wavelength / optics.na / optics.pixel_size


def _pupil_bins(optics: Optics, size: int, extent_px: float) -> int:
    """Pupil radius in frequency bins.

    The computed amplitude is periodic with period ``1 / dk = bins / (NA/λ)``;
    that period is kept >= ``_MIN_PERIOD_LAMBDA_NA`` λ/NA and >= ``size + 4``
    blur extents so that aliased amplitude tails stay ~1e-3 of the peak.
    """
    period_px = max(
        size + 4.0 * extent_px, _MIN_PERIOD_LAMBDA_NA / optics.cutoff / optics.pixel_size
    )
    return int(ceil(period_px * optics.pixel_size * optics.cutoff))


@lru_cache(maxsize=16)
def _pupil(noll: tuple[int, ...], optics: Optics, bins: int):
    """Pupil sampled on a ``(M, M)`` grid of spacing ``dk = (NA/λ) / bins``, ``M = 2 bins + 3``.

    Returns
    -------
    k : ndarray (M,)
        Frequencies of the grid axes, cycles/µm (symmetric about 0).
    index : ndarray (P,)
        Flat indices of the bins touched by the pupil.
    weight : ndarray (P,)
        Pupil transmission in [0, 1] (linear edge anti-aliasing over one bin).
    modes : ndarray (len(noll), P)
        ``Z_j`` at those bins.
    """
    dk = optics.cutoff / bins
    k = dk * np.arange(-(bins + 1), bins + 2)
    ky, kx = np.meshgrid(k, k, indexing="ij")
    kr = np.hypot(ky, kx).ravel()
    weight = np.clip((optics.cutoff - kr) / dk + 0.5, 0.0, 1.0)
    index = np.flatnonzero(weight)
    rho = kr[index] / optics.cutoff
    theta = np.arctan2(ky.ravel()[index], kx.ravel()[index])
    modes = np.array([zernike(j, rho, theta) for j in noll]).reshape(len(noll), index.size)
    return k, index, weight[index], modes


@lru_cache(maxsize=16)
def _window(optics: Optics, size: int, bins: int):
    """Fine sampling window of the intensity and the matrices that act on it.

    Returns
    -------
    dft : ndarray (Nw, M), complex
        ``exp(2 i π x_i k_m)``: amplitude at the fine samples ``x_i`` (µm,
        ``x = 0`` at index ``Nw // 2``) from pupil samples ``k_m``.
    transfer : ndarray (Nw, Nw // 2 + 1)
        Pixel transfer function ``sinc(p ky) sinc(p kx)`` on the rfft grid.
    samples : ndarray (size,)
        Fine indices of the output pixel centres.
    """
    q = optics.oversampling
    spacing = optics.pixel_size / q
    n = sfft.next_fast_len(q * (size + 2 * _WINDOW_MARGIN_PX), real=True)
    x = spacing * (np.arange(n) - n // 2)
    k = _pupil((), optics, bins)[0]
    dft = np.exp(2j * np.pi * np.multiply.outer(x, k))
    ky, kx = sfft.fftfreq(n, spacing), sfft.rfftfreq(n, spacing)
    transfer = np.outer(np.sinc(optics.pixel_size * ky), np.sinc(optics.pixel_size * kx))
    samples = n // 2 + q * (np.arange(size) - size // 2)
    return dft, transfer, samples


def psf_stack(
    noll: tuple[int, ...],
    coefs: np.ndarray,
    shifts: np.ndarray,
    optics: Optics,
    size: int,
    *,
    diameters: np.ndarray | None = None,
    drift: tuple[float, float] | None = None,
) -> np.ndarray:
    """Pixel-integrated PSFs for many aberration vectors and sub-pixel shifts.

    The amplitude is computed on a fine window (spacing ``p / q``) by a
    matrix Fourier transform of the pupil (exact for the sampled pupil, no FFT
    wrap-around of the window), normalised with Parseval's identity (so the
    intensity integrates to 1 over the whole plane, inside the window or not),
    then integrated over the pixels in Fourier space and sampled.

    Parameters
    ----------
    noll : tuple of int
        Noll indices of the columns of ``coefs``.
    coefs : ndarray, shape (B, len(noll))
        Zernike coefficients, waves rms.
    shifts : ndarray, shape (B, 2)
        Shift ``(row, col)`` of each PSF centre from pixel ``size // 2``, pixels.
    optics : Optics
    size : int
        Side of the output windows (odd).
    diameters : ndarray, shape (B,), or None
        Diameters (µm) of uniform fluorescent spheres imaged instead of point
        sources (:func:`sphere_transfer`); ``None``: points.
    drift : (float, float) or None
        Linear motion ``(dy, dx)`` (pixels) during the exposure, centred on
        the PSF position (:func:`_drift_transfer`); ``None``: no motion.

    Returns
    -------
    ndarray, shape (B, size, size), float64
        Non-negative pixel values: integrals over each pixel of the intensity
        normalised to unit integral over the plane.

    Notes
    -----
    Bead size and drift are real, even object filters multiplying the
    spectrum of the finely sampled intensity (band limited and Nyquist
    sampled, so the product is the exact convolution up to the periodic
    wrap-around of the fine window, which callers keep away from the output
    with :func:`object_pad`).

    An ``optics`` with a ``psf_stack(noll, coefs, shifts, size, *, diameters, drift)``
    method (a subclass of :class:`Optics`) computes the PSFs itself: the scene, the
    effects and the camera stay the simulator's, the optics are another code's (the
    benches' independent generator, ``bench/independent.py``).
    """
    shifts = np.asarray(shifts, float).reshape(-1, 2)
    coefs = np.asarray(coefs, float).reshape(len(shifts), len(noll))
    external = getattr(optics, "psf_stack", None)
    if external is not None:  # optics computed by other code (an independent generator)
        return external(noll, coefs, shifts, size, diameters=diameters, drift=drift)
    extent = float(_blur_radius(noll, coefs, optics).max(initial=0.0))
    bins = _pupil_bins(optics, size, extent)
    k, index, weight, modes = _pupil(noll, optics, bins)
    dft, transfer, samples = _window(optics, size, bins)
    m, n = k.size, dft.shape[0]
    ky, kx = (a.ravel()[index] for a in np.meshgrid(k, k, indexing="ij"))
    # |A|^2 dk^2 d^2 / sum |P|^2 are the fine samples of the unit-integral intensity.
    scale = (optics.cutoff / bins * optics.pixel_size / optics.oversampling) ** 2
    scale *= optics.oversampling**2 / np.sum(weight**2)  # q^2: fine samples -> pixel integrals

    out = np.empty((coefs.shape[0], size, size))
    batch = max(1, _BATCH_ELEMENTS // (n * max(n, m)))
    for start in range(0, coefs.shape[0], batch):
        sl = slice(start, start + batch)
        b = len(coefs[sl])
        # Wavefront in waves; the sub-pixel shift is a phase ramp on the pupil.
        wave = coefs[sl] @ modes - np.multiply.outer(shifts[sl, 0] * optics.pixel_size, ky)
        wave -= np.multiply.outer(shifts[sl, 1] * optics.pixel_size, kx)
        pupil = np.zeros((b, m * m), complex)
        pupil[:, index] = weight * np.exp(2j * np.pi * wave)
        half = pupil.reshape(b * m, m) @ dft.T  # (b*m, n): x transform
        half = half.reshape(b, m, n).transpose(1, 0, 2).reshape(m, b * n)
        amplitude = (dft @ half).reshape(n, b, n).transpose(1, 0, 2)  # y transform
        intensity = amplitude.real**2 + amplitude.imag**2
        spectrum = sfft.rfft2(intensity, workers=-1) * transfer
        if diameters is not None or drift is not None:
            spectrum *= _object_transfer(
                optics, n, None if diameters is None else diameters[sl], drift
            )
        image = sfft.irfft2(spectrum, s=(n, n), workers=-1)
        out[sl] = image[:, samples][:, :, samples] * scale
    return np.maximum(out, 0.0, out=out)  # clear FFT round-off negatives (~1e-18)


def _drift_transfer(ky: np.ndarray, kx: np.ndarray, drift_um: tuple[float, float]) -> np.ndarray:
    """Transform ``sinc(k . d)`` of the uniform average along the segment ``[-d/2, d/2]``."""
    return np.sinc(ky * drift_um[0] + kx * drift_um[1])


def _object_transfer(
    optics: Optics,
    n: int,
    diameters: np.ndarray | None,
    drift: tuple[float, float] | None,
) -> np.ndarray:
    """Product of the bead-size and drift filters on the rfft grid of the fine window.

    Returns an array broadcastable to ``(B, n, n // 2 + 1)``.
    """
    spacing = optics.pixel_size / optics.oversampling
    ky = sfft.fftfreq(n, spacing)[:, None]
    kx = sfft.rfftfreq(n, spacing)[None, :]
    out = np.ones((1, n, n // 2 + 1))
    if diameters is not None:
        k = np.hypot(ky, kx)
        out = out * sphere_transfer(k[None], np.asarray(diameters, float)[:, None, None])
    if drift is not None:
        out = out * _drift_transfer(
            ky, kx, (drift[0] * optics.pixel_size, drift[1] * optics.pixel_size)
        )
    return out


def object_pad(
    optics: Optics, diameters: np.ndarray | None, drift: tuple[float, float] | None
) -> int:
    """Extra window radius (pixels) that holds the spread of the bead-size/drift filters."""
    half = 0.0
    if diameters is not None and len(diameters):
        half += float(np.max(diameters)) / optics.pixel_size / 2.0
    if drift is not None:
        half += float(np.hypot(*drift)) / 2.0
    return int(ceil(half)) + 1 if half > 0 else 0


#: Highest Noll index a PSF takes: radial order 20, far beyond the aberrations a
#: microscope's pupil holds (the pupil's sampling grows with the order).
MAX_NOLL = 231


def _split_zernike(zernike_coefs: Mapping[int, float] | None) -> tuple[tuple[int, ...], np.ndarray]:
    items = []
    for j, c in (zernike_coefs or {}).items():
        try:
            jj, cc = int(j), float(c)
        except (TypeError, ValueError):
            raise ValueError(f"`zernike` must map Noll indices to waves rms, got "
                             f"{j!r}: {c!r}") from None
        if jj != j or not 1 <= jj <= MAX_NOLL:
            raise ValueError(f"`zernike`: Noll index {j!r} must be a whole number from 1 to "
                             f"{MAX_NOLL}")
        if not np.isfinite(cc):
            raise ValueError(f"`zernike`: the coefficient of Noll index {jj} must be finite, "
                             f"got {c!r}")
        items.append((jj, cc))
    items.sort()
    return tuple(j for j, _ in items), np.array([c for _, c in items], float)


def check_size(size: int) -> int:
    if int(size) != size or size < 1 or size % 2 == 0:
        raise ValueError(f"size must be a positive odd integer, got {size!r}")
    return int(size)


def simulate_psf(
    zernike: Mapping[int, float] | None = None,
    *,
    optics: Optics = Optics(),  # noqa: B008  (frozen dataclass, immutable default)
    size: int = 33,
    shift: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """Pixel-integrated widefield PSF with Zernike aberrations.

    Parameters
    ----------
    zernike : Mapping[int, float] or None
        Noll index -> coefficient in waves rms (Noll normalisation). ``None``:
        aberration-free.
    optics : Optics
        NA, emission wavelength (µm) and camera pixel size (µm).
    size : int
        Odd side of the output window, pixels.
    shift : tuple of float
        Sub-pixel (or any) displacement ``(row, col)`` of the PSF centre from
        pixel ``size // 2``, in pixels.

    Returns
    -------
    ndarray, shape (size, size), float64
        Non-negative pixel values (fraction of the photons falling in each
        pixel). The PSF integrates to 1 over the whole plane, so the sum over a
        window much larger than the PSF is ~1.
    """
    size = check_size(size)
    # the fine window (oversampled, with its margin): its complex amplitude, intensity,
    # spectrum and the transforms' buffers, about four complex arrays of it
    fine = optics.oversampling * (size + 2 * _WINDOW_MARGIN_PX)
    check_memory(4 * 16.0 * fine * fine, f"`size` {size}: a PSF window of {size} px, "
                 f"{fine} fine samples a side")
    noll, coefs = _split_zernike(zernike)
    try:
        sh = np.asarray(shift, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"`shift` must be two finite numbers (row, col), got {shift!r}") \
            from None
    if sh.shape != (2,) or not np.isfinite(sh).all():
        raise ValueError(f"`shift` must be two finite numbers (row, col), got {shift!r}")
    return psf_stack(noll, coefs[None], sh[None], optics, size)[0]


# ---------------------------------------------------------------------------
# Field PSFs and bead images
# ---------------------------------------------------------------------------


def _energy_radius(psf: np.ndarray, fraction: float) -> float:
    """Smallest radius (pixels, about the window centre) enclosing ``fraction`` of unit energy.

    ``inf`` if the window does not hold that fraction.
    """
    c = psf.shape[-1] // 2
    yy, xx = np.indices(psf.shape[-2:]) - c
    radius = np.hypot(yy, xx).ravel()
    order = np.argsort(radius, kind="stable")
    energy = np.cumsum(np.clip(psf.reshape(-1)[order], 0, None))
    hit = np.searchsorted(energy, fraction)
    return float(radius[order][hit]) if hit < energy.size else np.inf


@lru_cache(maxsize=32)
def field_psf_radius(
    aberrations: FieldAberrations,
    optics: Optics,
    shape: tuple[int, int],
    fraction: float = PSF_ENERGY_FRACTION,
) -> int:
    """``psf_radius`` of a field: max energy radius over corners, edge middles and centre."""
    ys = np.array([0.0, (shape[0] - 1) / 2.0, shape[0] - 1.0])
    xs = np.array([0.0, (shape[1] - 1) / 2.0, shape[1] - 1.0])
    yy, xx = (a.ravel() for a in np.meshgrid(ys, xs, indexing="ij"))
    coefs = aberrations.coefficient_matrix(yy, xx, shape)
    noll = aberrations.noll_indices
    extent = float(_blur_radius(noll, coefs, optics).max())
    size = 2 * ceil(3.0 * extent) + 1
    while True:
        psfs = psf_stack(noll, coefs, np.zeros((len(yy), 2)), optics, size)
        radius = max(_energy_radius(p, fraction) for p in psfs)
        if np.isfinite(radius):
            return max(4, ceil(radius - 1e-9))
        size = 2 * size + 1
