"""Simulator of fluorescent micro-bead images with a known space-varying PSF.

This is the test bench of the package: it produces bead images degraded by a
product-convolution operator whose ground truth is known exactly.

Model (eq. (6) of Debarnot, Escande, Mangeat & Weiss, "Learning low-dimensional
models of microscopes", section 3.1.1): the PSF at field position ``z`` is

.. math:: h_z = |\\mathcal{F}(P \\exp(2 i \\pi W_z))|^2, \\qquad
          W_z = \\sum_j c_j(z) Z_j,

with ``P`` the indicator of the pupil disk of radius ``NA / λ`` (cycles/µm),
``Z_j`` the rms-normalised Noll Zernike polynomials (:mod:`.zernike`) and
``c_j(z)`` smooth low-degree polynomials of the field position
(:class:`FieldAberrations`).

Numerics (:func:`_psf_stack`): the amplitude is the matrix Fourier transform
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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from math import ceil
from typing import Any

import numpy as np
from scipy import fft as sfft

from ..beads.sphere import sphere_transfer
from .zernike import zernike

__all__ = [
    "EFFECTS",
    "FieldAberrations",
    "Optics",
    "SimulationTruth",
    "simulate_beads",
    "simulate_psf",
]

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
#: Monomials of the field polynomials, in the order of ``FieldAberrations.terms``.
FIELD_BASIS = ("1", "u", "v", "u^2", "u*v", "v^2")

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


def _field_uv(y, x, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Normalised field coordinates ``u`` (columns) and ``v`` (rows) in [-1, 1]."""
    half_h = max((shape[0] - 1) / 2.0, 0.5)
    half_w = max((shape[1] - 1) / 2.0, 0.5)
    u = (np.asarray(x, float) - (shape[1] - 1) / 2.0) / half_w
    v = (np.asarray(y, float) - (shape[0] - 1) / 2.0) / half_h
    return u, v


def _field_basis(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Monomials ``(1, u, v, u^2, u v, v^2)`` stacked on a new last axis."""
    u, v = np.broadcast_arrays(u, v)
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1)


@dataclass(frozen=True)
class FieldAberrations:
    """Zernike coefficients as smooth low-degree polynomials of the field position.

    Coefficients are in waves rms (Noll normalisation). The field coordinates
    ``(u, v)`` are normalised to ``[-1, 1]``: ``u`` along columns (x), ``v``
    along rows (y), ``(0, 0)`` at the field centre, ``±1`` at the centres of
    the border pixels.

    Parameters
    ----------
    terms : Mapping[int, tuple of float]
        Noll index ``j`` -> polynomial coefficients in the basis
        ``(1, u, v, u^2, u*v, v^2)``; shorter tuples are zero padded.
    """

    terms: Mapping[int, tuple[float, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        clean: dict[int, tuple[float, ...]] = {}
        for j, coefs in dict(self.terms).items():
            if int(j) < 1:
                raise ValueError(f"Noll index must be >= 1, got {j}")
            coefs = tuple(float(c) for c in np.atleast_1d(coefs))
            if len(coefs) > len(FIELD_BASIS):
                raise ValueError(
                    f"term {j}: at most {len(FIELD_BASIS)} coefficients {FIELD_BASIS}, "
                    f"got {len(coefs)}"
                )
            clean[int(j)] = coefs + (0.0,) * (len(FIELD_BASIS) - len(coefs))
        object.__setattr__(self, "terms", dict(sorted(clean.items())))

    def __hash__(self) -> int:
        return hash(tuple(self.terms.items()))

    @property
    def noll_indices(self) -> tuple[int, ...]:
        """Noll indices with a (possibly zero) polynomial, increasing."""
        return tuple(self.terms)

    def coefficient_matrix(self, y, x, shape: tuple[int, int]) -> np.ndarray:
        """Zernike coefficients at many field positions.

        Parameters
        ----------
        y, x : array_like
            Row and column positions in pixels, broadcastable shapes ``S``.
        shape : tuple of int
            ``(H, W)`` of the image the positions refer to.

        Returns
        -------
        ndarray, shape ``S + (len(noll_indices),)``
            Coefficients in waves rms, columns ordered as :attr:`noll_indices`.
        """
        basis = _field_basis(*_field_uv(y, x, shape))
        poly = np.array([self.terms[j] for j in self.noll_indices], float).reshape(-1, 6)
        return basis @ poly.T

    def coefficients(self, y: float, x: float, shape: tuple[int, int]) -> dict[int, float]:
        """Zernike coefficients ``{noll j: waves rms}`` at pixel ``(y, x)`` of image ``shape``."""
        values = self.coefficient_matrix(float(y), float(x), shape)
        return {j: float(c) for j, c in zip(self.noll_indices, values, strict=True)}

    @classmethod
    def preset(cls, name: str) -> FieldAberrations:
        """Named aberration field.

        Parameters
        ----------
        name : {"none", "moderate", "strong"}
            ``"moderate"``: defocus from a tilted coverslip, astigmatism
            growing as the squared field radius, field-linear coma, a little
            spherical aberration. ``"strong"``: tilted and curved coverslip
            (defocus with a quadratic term), stronger astigmatism and coma.

        Returns
        -------
        FieldAberrations
        """
        try:
            return cls(_PRESETS[name])
        except KeyError:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(_PRESETS)}") from None

    @classmethod
    def random(
        cls,
        strength: float,
        seed: int | np.random.Generator | None = None,
        noll: Sequence[int] = (4, 5, 6, 7, 8, 11),
    ) -> FieldAberrations:
        """Random low-degree (<= 2) polynomial aberration field.

        Each coefficient of each polynomial is drawn from a centred normal law
        with standard deviation ``strength / sqrt(6)``, so that the rms of each
        Zernike coefficient over the field is of the order of ``strength``.

        Parameters
        ----------
        strength : float
            Typical rms (over the field) of each Zernike coefficient, waves rms.
        seed : int, Generator or None
            Seed of :func:`numpy.random.default_rng`.
        noll : sequence of int
            Noll indices that receive a random polynomial.

        Returns
        -------
        FieldAberrations
        """
        if strength < 0:
            raise ValueError(f"strength must be >= 0, got {strength}")
        rng = np.random.default_rng(seed)
        scale = strength / np.sqrt(len(FIELD_BASIS))
        return cls({j: tuple(rng.normal(0.0, scale, len(FIELD_BASIS))) for j in noll})


#               1      u      v      u^2    u*v    v^2
_PRESETS: dict[str, dict[int, tuple[float, ...]]] = {
    "none": {},
    "moderate": {
        4: (0.0, 0.075, 0.05, 0.0, 0.0, 0.0),
        5: (0.0, 0.0, 0.0, 0.0, 0.12, 0.0),
        6: (0.0, 0.0, 0.0, 0.06, 0.0, -0.06),
        7: (0.0, 0.0, 0.03, 0.0, 0.0, 0.0),
        8: (0.0, 0.03, 0.0, 0.0, 0.0, 0.0),
        11: (0.02, 0.0, 0.0, 0.0, 0.0, 0.0),
    },
    "strong": {
        4: (-0.04, 0.09, 0.06, 0.08, 0.0, 0.08),
        5: (0.0, 0.0, 0.0, 0.0, 0.22, 0.0),
        6: (0.0, 0.0, 0.0, 0.11, 0.0, -0.11),
        7: (0.0, 0.0, 0.04, 0.0, 0.0, 0.0),
        8: (0.0, 0.04, 0.0, 0.0, 0.0, 0.0),
        11: (0.03, 0.0, 0.0, 0.0, 0.0, 0.0),
    },
}


def _as_aberrations(aberrations: str | FieldAberrations | None) -> FieldAberrations:
    if aberrations is None:
        return FieldAberrations()
    if isinstance(aberrations, str):
        return FieldAberrations.preset(aberrations)
    if isinstance(aberrations, FieldAberrations):
        return aberrations
    raise TypeError(
        f"aberrations must be a preset name, FieldAberrations or None, got {aberrations!r}"
    )


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


def _psf_stack(
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
    with :func:`_object_pad`).
    """
    shifts = np.asarray(shifts, float).reshape(-1, 2)
    coefs = np.asarray(coefs, float).reshape(len(shifts), len(noll))
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


def _object_pad(
    optics: Optics, diameters: np.ndarray | None, drift: tuple[float, float] | None
) -> int:
    """Extra window radius (pixels) that holds the spread of the bead-size/drift filters."""
    half = 0.0
    if diameters is not None and len(diameters):
        half += float(np.max(diameters)) / optics.pixel_size / 2.0
    if drift is not None:
        half += float(np.hypot(*drift)) / 2.0
    return int(ceil(half)) + 1 if half > 0 else 0


def _split_zernike(zernike_coefs: Mapping[int, float] | None) -> tuple[tuple[int, ...], np.ndarray]:
    items = sorted((int(j), float(c)) for j, c in (zernike_coefs or {}).items())
    return tuple(j for j, _ in items), np.array([c for _, c in items], float)


def _check_size(size: int) -> int:
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
    size = _check_size(size)
    noll, coefs = _split_zernike(zernike)
    return _psf_stack(noll, coefs[None], np.asarray(shift, float)[None], optics, size)[0]


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
def _field_psf_radius(
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
        psfs = _psf_stack(noll, coefs, np.zeros((len(yy), 2)), optics, size)
        radius = max(_energy_radius(p, fraction) for p in psfs)
        if np.isfinite(radius):
            return max(4, ceil(radius - 1e-9))
        size = 2 * size + 1


@dataclass(eq=False)
class SimulationTruth:
    """Ground truth of a :func:`simulate_beads` image.

    Attributes
    ----------
    shape : tuple of int
        ``(H, W)`` of the image.
    positions : ndarray, shape (M, 2), float64
        True bead centres ``(row, col)`` in pixels (pixel centres at integers).
    amplitudes : ndarray, shape (M,), float64
        Total photons emitted by each bead and collected (integral of its PSF
        times amplitude over the plane).
    background : ndarray, shape (H, W), float32
        Smooth background, photons per pixel.
    optics : Optics
    aberrations : FieldAberrations
    gain : float
        Camera gain, ADU per photo-electron.
    offset : float
        Camera offset, ADU.
    read_noise : float
        Read noise, electrons rms.
    psf_radius : int
        Recommended PSF radius ``r`` (pixels) for the estimator: the radius of
        the disk holding ``psf_energy`` (default 90 %) of the energy of the
        widest PSF in the field (corners, edge middles, centre), rounded up,
        at least 4.
    peak_snr : ndarray, shape (M,)
        Per-bead peak SNR ``peak / sqrt(peak + background + read_noise^2)``
        with ``peak`` the expected photons in the brightest pixel of the bead,
        in photo-electrons.
    effects : dict
        Ground truth of the injected effects (see the ``effects`` parameter
        of :func:`simulate_beads`): each switched-on effect's parameter under
        its own key plus the arrays that define it. Empty without effects.
    """

    shape: tuple[int, int]
    positions: np.ndarray
    amplitudes: np.ndarray
    background: np.ndarray
    optics: Optics
    aberrations: FieldAberrations
    gain: float
    offset: float
    read_noise: float
    psf_radius: int
    peak_snr: np.ndarray
    effects: dict[str, Any] = field(default_factory=dict)

    def _psfs(self, ys: np.ndarray, xs: np.ndarray, size: int | None) -> np.ndarray:
        """Centred true PSFs at ``(ys, xs)`` (flat arrays), each normalised to sum 1."""
        size = _check_size(2 * self.psf_radius + 1 if size is None else size)
        coefs = self.aberrations.coefficient_matrix(ys, xs, self.shape)
        psfs = _psf_stack(
            self.aberrations.noll_indices, coefs, np.zeros((len(ys), 2)), self.optics, size
        )
        return psfs / psfs.sum(axis=(-2, -1), keepdims=True)

    def psf_at(self, y: float, x: float, size: int | None = None) -> np.ndarray:
        """True PSF at field position ``(y, x)`` (pixels).

        Parameters
        ----------
        y, x : float
            Row and column of the field position, pixels.
        size : int or None
            Odd window side; default ``2 * psf_radius + 1``.

        Returns
        -------
        ndarray, shape (size, size), float64
            PSF centred on pixel ``size // 2`` (no sub-pixel shift), normalised
            to sum 1 over the window.
        """
        return self._psfs(np.array([float(y)]), np.array([float(x)]), size)[0]

    def observed_psf_at(
        self, y: float, x: float, size: int | None = None, *, diameter: float | None = None
    ) -> np.ndarray:
        """Image of a bead at ``(y, x)`` as the camera sees it, apart from noise.

        The optical PSF (:meth:`psf_at`) convolved with the projected bead
        profile and averaged along the drift, when those effects were
        simulated; camera effects (illumination, nonlinearity, offsets, hot
        pixels, saturation) are not included.

        Parameters
        ----------
        y, x : float
            Row and column of the field position, pixels.
        size : int or None
            Odd window side; default ``2 * psf_radius + 1``.
        diameter : float or None
            Bead diameter, µm; default the mean simulated diameter (0 without
            the ``"bead_size"`` effect).

        Returns
        -------
        ndarray, shape (size, size), float64
            Centred on pixel ``size // 2``, normalised to sum 1 over the window.
            Equals :meth:`psf_at` for point beads without drift.
        """
        if diameter is None:
            diameter = float(np.mean(self.effects.get("bead_size", (0.0, 0.0))))
        diameter = float(diameter)
        if not np.isfinite(diameter) or diameter < 0:
            raise ValueError(f"diameter must be >= 0 and finite, got {diameter!r}")
        drift = self.effects.get("drift")
        if diameter == 0 and drift is None:
            return self.psf_at(y, x, size)
        size = _check_size(2 * self.psf_radius + 1 if size is None else size)
        diameters = np.array([diameter]) if diameter > 0 else None
        pad = _object_pad(self.optics, diameters, drift)
        coefs = self.aberrations.coefficient_matrix(float(y), float(x), self.shape)[None]
        psf = _psf_stack(
            self.aberrations.noll_indices,
            coefs,
            np.zeros((1, 2)),
            self.optics,
            size + 2 * pad,
            diameters=diameters,
            drift=drift,
        )[0]
        psf = psf[pad : pad + size, pad : pad + size]
        return psf / psf.sum()

    def psf_grid(
        self,
        n_rows: int = 8,
        n_cols: int = 8,
        size: int | None = None,
        margin: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True PSFs on a regular grid of field positions.

        Parameters
        ----------
        n_rows, n_cols : int
            Number of grid rows and columns.
        size : int or None
            Odd window side; default ``2 * psf_radius + 1``.
        margin : float or None
            Distance (pixels) of the outermost positions from the border pixel
            centres; default ``psf_radius``.

        Returns
        -------
        ys : ndarray, shape (n_rows,)
            Row positions, pixels, evenly spaced in ``[margin, H - 1 - margin]``.
        xs : ndarray, shape (n_cols,)
            Column positions, pixels.
        psfs : ndarray, shape (n_rows, n_cols, size, size)
            ``psfs[i, k] == psf_at(ys[i], xs[k], size)``.
        """
        margin = float(self.psf_radius if margin is None else margin)
        ys = np.linspace(margin, self.shape[0] - 1 - margin, n_rows)
        xs = np.linspace(margin, self.shape[1] - 1 - margin, n_cols)
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        psfs = self._psfs(yy.ravel(), xx.ravel(), size)
        return ys, xs, psfs.reshape(n_rows, n_cols, *psfs.shape[-2:])


def _place_beads(
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


def _smooth_background(
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


def _render_beads(
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
    :func:`_psf_stack`; the window radius then grows by :func:`_object_pad`.
    """
    radius += _object_pad(optics, diameters, drift)
    size = 2 * radius + 1
    centres = np.rint(positions).astype(int)
    offsets = positions - centres
    coefs = aberrations.coefficient_matrix(positions[:, 0], positions[:, 1], image.shape)
    peaks = np.empty(len(positions))
    chunk = 64  # bounds the memory of the PSF stack
    for start in range(0, len(positions), chunk):
        sl = slice(start, start + chunk)
        if diameters is None and drift is None:
            psfs = _psf_stack(aberrations.noll_indices, coefs[sl], offsets[sl], optics, size)
        else:
            psfs = _psf_stack(
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


def _camera_adu(
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


def _digitise(adu: np.ndarray, dtype: np.dtype, level: float | None = None) -> np.ndarray:
    """Integer dtypes rounded and clipped to their range; everything clipped at ``level``."""
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        adu = np.clip(np.rint(adu), info.min, info.max if level is None else level)
    elif level is not None:
        adu = np.minimum(adu, level)
    return adu.astype(dtype)


def _camera(
    rng: np.random.Generator,
    photons: np.ndarray,
    gain: float,
    offset: float,
    read_noise: float,
    dtype: np.dtype,
) -> np.ndarray:
    """Poisson shot noise, gain, offset, Gaussian read noise; integer dtypes rounded, clipped."""
    return _digitise(_camera_adu(rng, photons, gain, offset, read_noise), dtype)


def _as_range(value: float | tuple[float, float], name: str) -> tuple[float, float]:
    low, high = (float(value), float(value)) if np.isscalar(value) else map(float, value)
    if not 0 <= low <= high:
        raise ValueError(f"{name} must satisfy 0 <= low <= high, got {value!r}")
    return low, high


# ---------------------------------------------------------------------------
# Injectable effects (the ``effects`` argument of simulate_beads)
# ---------------------------------------------------------------------------

#: Effect keys, in the order of the child generators spawned for them.
EFFECTS = (
    "illumination",
    "row_offsets",
    "column_offsets",
    "hot_pixels",
    "saturation",
    "nonlinearity",
    "neighbours",
    "bead_size",
    "drift",
    "background_structure",
)
_ILLUMINATION_MAX_SHIFT = 0.2  # random shift of the illumination centre, fraction of the field
_HOT_PIXEL_RANGE = (0.2, 1.0)  # hot-pixel values, fraction of the typical bead peak (ADU)
_COMPANION_DISTANCE = (0.6, 1.6)  # companion distance, units of psf_radius
_COMPANION_AMPLITUDE = (0.3, 1.0)  # companion amplitude, fraction of its bead's
_BLOB_SIGMA = (0.3, 0.6)  # background-structure blob sigma, units of psf_radius
_BLOB_SPACING = 3.0  # one blob per (_BLOB_SPACING * psf_radius)^2 of field


def _scalar(
    effect: str,
    value: Any,
    low: float,
    high: float,
    *,
    open_low: bool = True,
    open_high: bool = False,
) -> float:
    """``value`` as a float in the interval ``(low, high]`` (bounds open/closed as told)."""
    try:
        if isinstance(value, bool):
            raise TypeError
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"effect {effect!r}: expected a number, got {value!r}") from None
    above = out > low if open_low else out >= low
    below = out < high if open_high else out <= high
    if not (np.isfinite(out) and above and below):
        lo, hi = "(" if open_low else "[", ")" if open_high else "]"
        raise ValueError(
            f"effect {effect!r}: value must lie in {lo}{low:g}, {high:g}{hi}, got {value!r}"
        )
    return out


def _pair(effect: str, value: Any) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"effect {effect!r}: expected two numbers, got {value!r}") from None
    if not (np.isfinite(a) and np.isfinite(b)):
        raise ValueError(f"effect {effect!r}: expected finite numbers, got {value!r}")
    return a, b


def _check_effects(
    effects: Mapping[str, Any] | None,
    shape: tuple[int, int],
    dtype: np.dtype,
    offset: float,
) -> dict[str, Any]:
    """Validated, normalised effect parameters (see :func:`simulate_beads`)."""
    if effects is None:
        return {}
    if not isinstance(effects, Mapping):
        raise ValueError(f"effects must be a mapping or None, got {type(effects).__name__}")
    unknown = [k for k in effects if k not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect {unknown[0]!r}; valid effects: {', '.join(EFFECTS)}")
    out: dict[str, Any] = {}
    inf = np.inf
    for key, value in effects.items():
        if key == "illumination":
            if np.isscalar(value):
                out[key] = (_scalar(key, value, 0.0, 1.0, open_high=True), None)
            else:
                try:
                    strength, centre = value
                except (TypeError, ValueError):
                    raise ValueError(
                        f"effect {key!r}: expected s or (s, (row, col)), got {value!r}"
                    ) from None
                out[key] = (_scalar(key, strength, 0.0, 1.0, open_high=True), _pair(key, centre))
        elif key in ("row_offsets", "column_offsets", "background_structure"):
            out[key] = _scalar(key, value, 0.0, inf, open_low=False, open_high=True)
        elif key == "hot_pixels":
            factors = None
            if isinstance(value, (tuple, list)):  # (count or fraction, (low, high))
                try:
                    value, factors = value
                except (TypeError, ValueError):
                    raise ValueError(f"effect {key!r}: expected n, a fraction, or (n or "
                                     f"fraction, (low, high)), got {value!r}") from None
                factors = _pair(key, factors)
                if not 0 < factors[0] <= factors[1]:
                    raise ValueError(f"effect {key!r}: need 0 < low <= high, got {factors}")
            if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
                count = int(value)
            else:
                count = round(_scalar(key, value, 0.0, 1.0, open_high=True) * shape[0] * shape[1])
            if not 0 <= count <= shape[0] * shape[1]:
                raise ValueError(
                    f"effect {key!r}: count must lie in [0, {shape[0] * shape[1]}], got {value!r}"
                )
            out[key] = count if factors is None else (count, factors)
        elif key == "saturation":
            top = np.iinfo(dtype).max if np.issubdtype(dtype, np.integer) else inf
            level = _scalar(key, value, offset, top, open_high=True)
            out[key] = float(np.floor(level)) if np.issubdtype(dtype, np.integer) else level
        elif key == "nonlinearity":
            out[key] = _scalar(key, value, 0.0, 0.5)
        elif key == "neighbours":
            if isinstance(value, dict):
                unknown = sorted(set(value) - {"fraction", "distance_px", "amplitude"})
                if unknown or "fraction" not in value:
                    raise ValueError(f"effect {key!r}: a dict needs 'fraction' and may hold "
                                     f"'distance_px', 'amplitude'; got keys {sorted(value)}")
                dist = value.get("distance_px")
                if dist is not None:
                    dist = _pair(key, dist)
                    if not 0 < dist[0] <= dist[1]:
                        raise ValueError(f"effect {key!r}: need 0 < distance_px low <= high, "
                                         f"got {value['distance_px']!r}")
                amp = _pair(key, value.get("amplitude", _COMPANION_AMPLITUDE))
                if not 0 < amp[0] <= amp[1]:
                    raise ValueError(f"effect {key!r}: need 0 < amplitude low <= high, got "
                                     f"{value.get('amplitude')!r}")
                out[key] = {"fraction": _scalar(key, value["fraction"], 0.0, 1.0),
                            "distance_px": dist, "amplitude": amp}
            else:
                out[key] = _scalar(key, value, 0.0, 1.0)
        elif key == "bead_size":
            low, high = (value, value) if np.isscalar(value) else _pair(key, value)
            low = _scalar(key, low, 0.0, inf, open_low=False, open_high=True)
            high = _scalar(key, high, 0.0, inf, open_low=False, open_high=True)
            if low > high:
                raise ValueError(f"effect {key!r}: need d_min <= d_max, got {value!r}")
            out[key] = (low, high)
        elif key == "drift":
            out[key] = _pair(key, value)
    return out


def _illumination_map(
    rng: np.random.Generator, shape: tuple[int, int], strength: float, centre
) -> tuple[np.ndarray, Any]:
    """Centre of ``I = 1 - s rho^2`` and a function evaluating it at ``(y, x)``.

    ``rho`` is the distance to the centre divided by the distance from the
    centre to the farthest image corner (the half-diagonal for a centred
    field), so ``1 - s <= I <= 1``. Without an explicit centre, the field
    centre is shifted by a uniform random fraction (up to 20 %) of the field.
    """
    if centre is None:
        shift = rng.uniform(-_ILLUMINATION_MAX_SHIFT, _ILLUMINATION_MAX_SHIFT, 2)
        centre = (np.array(shape) - 1) / 2.0 + shift * np.array(shape)
    centre = np.asarray(centre, float)
    corners = np.array([[0, 0], [0, shape[1] - 1], [shape[0] - 1, 0], [shape[0] - 1, shape[1] - 1]])
    scale = max(float(np.hypot(*(corners - centre).T).max()), 1.0)

    def evaluate(y, x):
        rho2 = (np.asarray(y, float) - centre[0]) ** 2 + (np.asarray(x, float) - centre[1]) ** 2
        return 1.0 - strength * rho2 / scale**2

    return centre, evaluate


def _fixed_pattern(rng: np.random.Generator, n: int, sd: float) -> np.ndarray:
    """Per-row (or per-column) offsets, ADU, normal with standard deviation ``sd``."""
    return rng.normal(0.0, sd, n)


def _hot_pixels(
    rng: np.random.Generator, shape: tuple[int, int], count: int, peak_adu: float,
    factors: tuple[float, float] = _HOT_PIXEL_RANGE,
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` distinct pixels ``(row, col)`` with values uniform in ``factors`` times
    the peak."""
    flat = rng.choice(shape[0] * shape[1], size=count, replace=False)
    where = np.stack(np.unravel_index(np.sort(flat), shape), axis=1)
    values = peak_adu * rng.uniform(*factors, size=count)
    return where, values


def _nonlinear(electrons: np.ndarray, c: float, e_ref: float) -> np.ndarray:
    """Compressive response ``e (1 - c e / e_ref)``, monotone.

    Increasing for ``e <= e_ref / (2 c)`` (which holds up to ``e_ref`` since
    ``c <= 0.5``); held at its maximum ``e_ref / (4 c)`` beyond.
    """
    e = np.minimum(electrons, e_ref / (2.0 * c))
    return e * (1.0 - c * e / e_ref)


def _companions(
    rng: np.random.Generator, positions: np.ndarray, spec, radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Owner index, position and relative amplitude of companion beads.

    ``spec`` is a fraction ``f`` or a dict (``fraction``, ``distance_px``,
    ``amplitude``). ``round(f * M)`` distinct beads each get one companion at a
    distance uniform in ``[0.6, 1.6] * radius`` (or ``distance_px``) in a uniform
    direction, with an amplitude factor uniform in ``[0.3, 1]`` (or ``amplitude``).
    """
    if isinstance(spec, dict):
        fraction, dist, amp = spec["fraction"], spec["distance_px"], spec["amplitude"]
    else:
        fraction, dist, amp = spec, None, _COMPANION_AMPLITUDE
    dist = dist if dist is not None else tuple(radius * d for d in _COMPANION_DISTANCE)
    count = round(fraction * len(positions))
    owners = np.sort(rng.choice(len(positions), size=count, replace=False))
    distance = rng.uniform(*dist, size=count)
    angle = rng.uniform(0.0, 2.0 * np.pi, size=count)
    factor = rng.uniform(*amp, size=count)
    where = positions[owners] + distance[:, None] * np.stack([np.sin(angle), np.cos(angle)], 1)
    return owners, where, factor


def _bead_diameters(
    rng: np.random.Generator, n: int, d_range: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Diameters (µm) uniform in ``d_range`` and brightness factors ``d^3 / E[d^3]``."""
    low, high = d_range
    diameters = rng.uniform(low, high, size=n) if high > low else np.full(n, low)
    mean_cube = (high**4 - low**4) / (4.0 * (high - low)) if high > low else low**3
    factors = diameters**3 / mean_cube if mean_cube > 0 else np.ones(n)
    return diameters, factors


def _background_structure(
    rng: np.random.Generator, shape: tuple[int, int], peak: float, radius: float
) -> np.ndarray:
    """Sum of Gaussian blobs of peak ``peak`` photons, sigma in ``[0.3, 0.6] * radius``.

    Uniform centres over the field, about one per ``(3 radius)^2`` pixels:
    structure at the scale of a bead patch, wider than the PSF core. On
    ``2 r x 2 r`` patches an order-2 polynomial leaves about half of its rms
    (wider blobs, sigma up to ``r``, are mostly absorbed: a third).
    """
    count = max(1, round(shape[0] * shape[1] / (_BLOB_SPACING * radius) ** 2))
    centres = rng.uniform((0.0, 0.0), (shape[0] - 1.0, shape[1] - 1.0), size=(count, 2))
    sigmas = radius * rng.uniform(*_BLOB_SIGMA, size=count)
    out = np.zeros(shape)
    for (cy, cx), sigma in zip(centres, sigmas, strict=True):
        half = ceil(4.0 * sigma)
        y0, y1 = max(int(cy) - half, 0), min(int(cy) + half + 1, shape[0])
        x0, x1 = max(int(cx) - half, 0), min(int(cx) + half + 1, shape[1])
        gy = np.exp(-0.5 * ((np.arange(y0, y1) - cy) / sigma) ** 2)
        gx = np.exp(-0.5 * ((np.arange(x0, x1) - cx) / sigma) ** 2)
        out[y0:y1, x0:x1] += peak * np.outer(gy, gx)
    return out.astype(np.float32)


def _typical_peak(
    amplitudes: np.ndarray, peaks: np.ndarray, amp_range, aberrations, optics, shape
) -> float:
    """Median expected bead peak, photons (mean amplitude x PSF peak at the centre if no bead)."""
    if len(amplitudes):
        return float(np.median(amplitudes * peaks))
    centre = aberrations.coefficient_matrix((shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0, shape)
    psf = _psf_stack(aberrations.noll_indices, centre[None], np.zeros((1, 2)), optics, 9)
    return float(np.mean(amp_range) * psf.max())


def _spawn(rng: np.random.Generator, n: int) -> list[np.random.Generator]:
    """``n`` independent child generators of ``rng`` without drawing from its stream."""
    try:
        return rng.spawn(n)
    except (AttributeError, TypeError, ValueError):  # bit generator without a seed sequence
        return [np.random.default_rng(s) for s in rng.integers(0, 2**63, size=n)]


def simulate_beads(
    shape: tuple[int, int] = (1024, 1024),
    n_beads: int = 150,
    *,
    aberrations: str | FieldAberrations | None = "moderate",
    optics: Optics | None = None,
    amplitude: float | tuple[float, float] = (2e4, 6e4),
    background: float | tuple[float, float] = (50.0, 150.0),
    gain: float = 2.0,
    offset: float = 100.0,
    read_noise: float = 1.5,
    min_separation: float | None = None,
    border: float | None = None,
    dtype: np.dtype | type = np.uint16,
    seed: int | np.random.Generator | None = 0,
    psf_energy: float = PSF_ENERGY_FRACTION,
    effects: Mapping[str, Any] | None = None,
    bead_photons: np.ndarray | None = None,
) -> tuple[np.ndarray, SimulationTruth]:
    """Simulate a camera image of fluorescent beads seen through a space-varying PSF.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` image shape, pixels.
    n_beads : int
        Number of beads.
    aberrations : str, FieldAberrations or None
        Preset name (``"none"``, ``"moderate"``, ``"strong"``), explicit
        aberration field, or ``None`` (aberration-free).
    optics : Optics or None
        Default ``Optics()``.
    amplitude : float or (float, float)
        Total photons per bead, uniform in ``[low, high]``.
    background : float or (float, float)
        Smooth background, photons/pixel, rescaled to span ``[low, high]``.
    gain : float
        ADU per photo-electron.
    offset : float
        Camera offset, ADU.
    read_noise : float
        Read noise, electrons rms (``read_noise * gain`` ADU rms).
    min_separation : float or None
        Minimum distance between bead centres, pixels; default
        ``2.5 * psf_radius``.
    border : float or None
        Minimum distance of bead centres from the border pixel centres,
        pixels; default ``psf_radius``.
    dtype : numpy dtype
        Output dtype. Integer dtypes are rounded and clipped to their range;
        float dtypes are neither.
    seed : int, Generator or None
        Seed of the single :func:`numpy.random.default_rng` used for
        everything (positions, amplitudes, background, noise).
    psf_energy : float
        Energy fraction defining ``truth.psf_radius``.
    bead_photons : array_like of shape (n_beads,), optional
        Total photons of each bead, instead of drawing them uniformly from
        ``amplitude`` (e.g. a log-normal brightness spread,
        :mod:`~napari_psfspace.core.simulation.family`).
    effects : Mapping[str, Any] or None
        Effects beyond the PSF model to inject, each key switching one on
        (``r`` below is ``truth.psf_radius``); all recorded in
        ``truth.effects``:

        ``"illumination": s`` (``0 < s < 1``) or ``(s, (row, col))``
            Non-uniform excitation ``I = 1 - s rho^2`` (``rho``: distance to
            the centre over the distance from the centre to the farthest
            corner, so ``I >= 1 - s``) multiplying the bead amplitudes (at
            each bead) and the smooth background. The centre is the field
            centre shifted by a random fraction (up to 20 %) of the field, or
            ``(row, col)`` pixels. Truth: ``illumination_centre``,
            ``illumination_map`` (H, W) float32, ``illumination_factors`` (M,).
        ``"row_offsets": sd``, ``"column_offsets": sd`` (ADU)
            Fixed-pattern offsets, normal with standard deviation ``sd``, per
            row / column, added to the ADU image after the noise. Truth:
            ``row_offset_values`` (H,), ``column_offset_values`` (W,).
        ``"hot_pixels": n`` (int), a fraction of the pixels (float < 1), or ``(n, (lo, hi))``
            Distinct random pixels with an extra dark signal uniform in
            [20 %, 100 %] of the median expected bead peak (ADU) (with
            ``(lo, hi)``: uniform in ``lo``-``hi`` times the brightest expected
            bead peak, e.g. ``(0.001, (1, 5))`` for an sCMOS without dark-frame
            correction; ``n`` a count or a fraction), added
            (noiseless) to the ADU image after the noise. Truth:
            ``hot_pixels`` (the count), ``hot_pixel_positions`` (n, 2) int
            ``(row, col)``, ``hot_pixel_values`` (n,) ADU.
        ``"saturation": level`` (ADU, above ``offset``, below the dtype max)
            The final image is clipped at ``level`` (rounded down for
            integer dtypes). Truth: ``saturation`` (the level),
            ``saturated_pixels`` (number of pixels at the level).
        ``"nonlinearity": c`` (``0 < c <= 0.5``)
            Compressive response ``e (1 - c e / e_ref)`` applied to the
            expected electrons before the shot noise, with ``e_ref`` the
            brightest expected pixel (a bead peak, background included), which
            loses the fraction ``c``; increasing up to ``e_ref / (2 c) >=
            e_ref`` and held constant beyond, so monotone. Truth:
            ``nonlinearity_reference`` (``e_ref``, electrons).
        ``"neighbours": f`` (``0 < f <= 1``) or a dict ``fraction``, ``distance_px``, ``amplitude``
            ``round(f M)`` random beads get a companion at a distance uniform
            in ``[0.6 r, 1.6 r]`` (or ``distance_px``) in a random direction,
            amplitude uniform in [0.3, 1] (or ``amplitude``) times the bead's
            (before illumination), same diameter,
            rendered with the PSF at its own position (the minimum
            separation is violated on purpose). ``truth.positions`` stays
            the primary beads. Truth: ``companion_positions`` (K, 2),
            ``companion_amplitudes`` (K,) photons, ``companion_of`` (K,)
            index of the primary bead.
        ``"bead_size": d`` or ``(d_min, d_max)`` (µm)
            Beads are uniform spheres of diameter ``d`` (or uniform in
            ``[d_min, d_max]``, with amplitude times ``d^3 / E[d^3]``): the
            optical PSF convolved with the projected sphere. Truth:
            ``bead_size`` ``(d_min, d_max)``, ``bead_diameters`` (M,) µm,
            ``companion_diameters`` (K,) with ``"neighbours"``.
        ``"drift": (dy, dx)`` (pixels)
            Linear sample motion during the exposure: each bead image is the
            PSF averaged along the segment from ``-(dy, dx) / 2`` to
            ``+(dy, dx) / 2`` about its (mid-exposure) position. Truth:
            ``drift``; :meth:`SimulationTruth.observed_psf_at` includes it.
        ``"background_structure": a`` (photons)
            Additive sum of Gaussian blobs of peak ``a``, sigma uniform in
            ``[0.3 r, 0.6 r]``, uniform centres, about one per ``(3 r)^2``
            pixels (structure at the scale of a bead patch that an order-2
            polynomial per patch does not describe). Not illuminated. Truth:
            ``background_structure_map`` (H, W) float32.

        Invalid keys or values raise ValueError. The randomness of each effect
        comes from its own child of the seeded generator
        (:meth:`numpy.random.Generator.spawn`, one per key of ``EFFECTS`` in
        that order), so effects draw nothing from the main stream: positions,
        amplitude factors and smooth background equal those of
        ``effects=None``, each effect's realisation does not depend on the
        other effects, and effects that do not change the expected photons
        (offsets, hot pixels, saturation) leave the noise realisation
        unchanged. ``effects=None`` (or ``{}``) is bit-identical to not
        passing it.

    Returns
    -------
    image : ndarray, shape (H, W), ``dtype``
        Camera image in ADU.
    truth : SimulationTruth
        Positions, amplitudes, background, optics, aberrations, camera
        parameters, recommended PSF radius, per-bead peak SNR and effects.
        With effects, ``amplitudes`` are the photons collected from each
        primary bead (bead-size and illumination factors included) and
        ``background`` is the expected background photons in the image
        (illuminated smooth background plus background structure).

    Raises
    ------
    ValueError
        If the beads cannot be placed with the requested separation/border,
        or for an unknown effect or an invalid effect value.

    Notes
    -----
    Each bead is rendered with the exact PSF at its own position (Zernike
    coefficients evaluated there) and sub-pixel offset, on a window of radius
    ``RENDER_RADIUS_FACTOR * psf_radius`` (clipped at the image border).
    """
    shape = (int(shape[0]), int(shape[1]))
    n_beads = int(n_beads)
    if n_beads < 0:
        raise ValueError(f"n_beads must be >= 0, got {n_beads}")
    optics = Optics() if optics is None else optics
    aberrations = _as_aberrations(aberrations)
    amp_range = _as_range(amplitude, "amplitude")
    bg_range = _as_range(background, "background")
    dtype = np.dtype(dtype)
    effect_params = _check_effects(effects, shape, dtype, offset)
    if not 0.0 < psf_energy < 1.0:
        raise ValueError(f"psf_energy must be in (0, 1), got {psf_energy!r}")
    rng = np.random.default_rng(seed)

    psf_radius = _field_psf_radius(aberrations, optics, shape, psf_energy)
    border = float(psf_radius if border is None else border)
    min_separation = float(2.5 * psf_radius if min_separation is None else min_separation)

    positions = _place_beads(rng, shape, n_beads, min_separation, border)
    if bead_photons is None:
        amplitudes = rng.uniform(*amp_range, size=n_beads)
    else:
        amplitudes = np.asarray(bead_photons, dtype=np.float64).reshape(-1)
        if len(amplitudes) != n_beads or np.any(~np.isfinite(amplitudes)) or np.any(
                amplitudes < 0):
            raise ValueError(f"bead_photons must hold n_beads={n_beads} finite non-negative "
                             f"numbers, got shape {np.shape(bead_photons)}")
        if n_beads:
            amp_range = (float(amplitudes.min()), float(amplitudes.max()))
    bg = _smooth_background(rng, shape, *bg_range)
    if effect_params:
        return _simulate_with_effects(
            rng,
            effect_params,
            shape,
            positions,
            amplitudes,
            bg,
            aberrations,
            optics,
            amp_range,
            gain,
            offset,
            read_noise,
            dtype,
            psf_radius,
        )

    photons = bg.astype(np.float64)
    peaks = _render_beads(
        photons, positions, amplitudes, aberrations, optics, RENDER_RADIUS_FACTOR * psf_radius
    )
    image = _camera(rng, photons, gain, offset, read_noise, dtype)

    peak = amplitudes * peaks
    centres = np.clip(np.rint(positions).astype(int), 0, np.array(shape) - 1)
    local_bg = bg[centres[:, 0], centres[:, 1]].astype(np.float64)
    truth = SimulationTruth(
        shape=shape,
        positions=positions,
        amplitudes=amplitudes,
        background=bg,
        optics=optics,
        aberrations=aberrations,
        gain=float(gain),
        offset=float(offset),
        read_noise=float(read_noise),
        psf_radius=psf_radius,
        peak_snr=peak / np.sqrt(peak + local_bg + read_noise**2),
    )
    return image, truth


def _simulate_with_effects(
    rng: np.random.Generator,
    params: dict[str, Any],
    shape: tuple[int, int],
    positions: np.ndarray,
    amplitudes: np.ndarray,
    bg: np.ndarray,
    aberrations: FieldAberrations,
    optics: Optics,
    amp_range: tuple[float, float],
    gain: float,
    offset: float,
    read_noise: float,
    dtype: np.dtype,
    psf_radius: int,
) -> tuple[np.ndarray, SimulationTruth]:
    """The rest of :func:`simulate_beads` with the validated ``params`` effects injected.

    Order: bead sizes (amplitude factors), companions, illumination (beads
    and smooth background), background structure, rendering (bead size,
    drift), nonlinearity, camera noise (main generator, as without effects),
    row/column offsets, hot pixels, saturation and digitisation.
    """
    rngs = dict(zip(EFFECTS, _spawn(rng, len(EFFECTS)), strict=True))
    fx: dict[str, Any] = {}
    n = len(positions)
    amplitudes = amplitudes.astype(np.float64)
    diameters = None
    if "bead_size" in params:
        diameters, factors = _bead_diameters(rngs["bead_size"], n, params["bead_size"])
        amplitudes = amplitudes * factors
        fx.update(bead_size=params["bead_size"], bead_diameters=diameters)

    all_pos, all_amp, all_diam = positions, amplitudes, diameters
    if "neighbours" in params:
        owners, comp_pos, comp_factor = _companions(
            rngs["neighbours"], positions, params["neighbours"], psf_radius
        )
        all_pos = np.concatenate([positions, comp_pos])
        all_amp = np.concatenate([amplitudes, comp_factor * amplitudes[owners]])
        if diameters is not None:
            all_diam = np.concatenate([diameters, diameters[owners]])

    background = bg.astype(np.float64)
    if "illumination" in params:
        strength, centre = params["illumination"]
        centre, illumination = _illumination_map(rngs["illumination"], shape, strength, centre)
        field_map = illumination(np.arange(shape[0])[:, None], np.arange(shape[1])[None, :])
        factors = illumination(all_pos[:, 0], all_pos[:, 1])
        all_amp = all_amp * factors
        background *= field_map
        fx.update(
            illumination=strength,
            illumination_centre=centre,
            illumination_map=field_map.astype(np.float32),
            illumination_factors=factors[:n],
        )
    if "background_structure" in params:
        structure = _background_structure(
            rngs["background_structure"], shape, params["background_structure"], psf_radius
        )
        background += structure
        fx.update(
            background_structure=params["background_structure"],
            background_structure_map=structure,
        )
    if "neighbours" in params:
        fx.update(
            neighbours=params["neighbours"],
            companion_positions=all_pos[n:],
            companion_amplitudes=all_amp[n:],
            companion_of=owners,
        )
        if diameters is not None:
            fx["companion_diameters"] = all_diam[n:]
    drift = params.get("drift")
    if drift is not None:
        fx["drift"] = drift

    photons = background.copy()
    peaks = _render_beads(
        photons,
        all_pos,
        all_amp,
        aberrations,
        optics,
        RENDER_RADIUS_FACTOR * psf_radius,
        all_diam,
        drift,
    )[:n]
    amplitudes = all_amp[:n]

    if "nonlinearity" in params:
        e_ref = float(photons.max())
        photons = _nonlinear(photons, params["nonlinearity"], e_ref)
        fx.update(nonlinearity=params["nonlinearity"], nonlinearity_reference=e_ref)
    adu = _camera_adu(rng, photons, gain, offset, read_noise)
    if "row_offsets" in params:
        rows = _fixed_pattern(rngs["row_offsets"], shape[0], params["row_offsets"])
        adu += rows[:, None]
        fx.update(row_offsets=params["row_offsets"], row_offset_values=rows)
    if "column_offsets" in params:
        cols = _fixed_pattern(rngs["column_offsets"], shape[1], params["column_offsets"])
        adu += cols[None, :]
        fx.update(column_offsets=params["column_offsets"], column_offset_values=cols)
    if "hot_pixels" in params:
        hot = params["hot_pixels"]
        if isinstance(hot, tuple):  # factors of the brightest expected bead peak
            count, factors = hot
            top = float(np.max(amplitudes * peaks)) if len(amplitudes) else 0.0
            where, values = _hot_pixels(rngs["hot_pixels"], shape, count, gain * top, factors)
        else:
            count = hot
            typical = gain * _typical_peak(amplitudes, peaks, amp_range, aberrations, optics,
                                           shape)
            where, values = _hot_pixels(rngs["hot_pixels"], shape, count, typical)
        adu[where[:, 0], where[:, 1]] += values
        fx.update(hot_pixels=count, hot_pixel_positions=where, hot_pixel_values=values)
    level = params.get("saturation")
    if level is not None:
        rounded = np.rint(adu) if np.issubdtype(dtype, np.integer) else adu
        fx.update(saturation=level, saturated_pixels=int(np.count_nonzero(rounded >= level)))
    image = _digitise(adu, dtype, level)

    peak = amplitudes * peaks
    centres = np.clip(np.rint(positions).astype(int), 0, np.array(shape) - 1)
    local_bg = background[centres[:, 0], centres[:, 1]]
    truth = SimulationTruth(
        shape=shape,
        positions=positions,
        amplitudes=amplitudes,
        background=background.astype(np.float32),
        optics=optics,
        aberrations=aberrations,
        gain=float(gain),
        offset=float(offset),
        read_noise=float(read_noise),
        psf_radius=psf_radius,
        peak_snr=peak / np.sqrt(peak + local_bg + read_noise**2),
        effects=fx,
    )
    return image, truth
