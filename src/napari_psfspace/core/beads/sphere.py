"""Beads are spheres: their images are the PSF blurred by the sphere's projection.

A bead of diameter ``d`` is a uniform fluorescent ball; its image is ``h * S(d)``, the
optical PSF ``h`` convolved with the ball's projection (chord-length profile), whose
Fourier transform is ``T(d, k) = 3 (sin q - q cos q) / q^3`` with ``q = pi d |k|``
(:func:`sphere_transfer`). This module changes the size of bead images
(:func:`change_size`, used by the bead-size effect of the diagnosis) and removes a known
bead size from learnt PSFs (:func:`remove_sphere`: a 200 nm bead at 100 nm pixels is 2 px
wide, and the model learns ``h * S(2 px)`` unless told).
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

from ..common.progress import check_halt

#: Largest gain :func:`remove_sphere` applies at any frequency (``1 / T`` is capped there).
MAX_GAIN = 10.0
#: First zero of ``sin q - q cos q`` (``tan q = q``): the sphere's transfer vanishes at
#: ``|k| = FIRST_ZERO_Q / (pi d)``.
FIRST_ZERO_Q = 4.493409457909064


def sphere_transfer(k, diameter) -> np.ndarray:
    """2-D Fourier transform of the projected (chord-length) profile of a uniform sphere.

    The projection of a ball onto the image plane is, in Fourier space, the
    3-D transform of the ball on the plane ``k_z = 0``:
    ``3 (sin q - q cos q) / q^3`` with ``q = π d |k|``, normalised to 1 at
    ``k = 0`` (unit total intensity). Any length unit, the same for both:
    ``d`` in µm with ``|k|`` in cycles/µm, or pixels with cycles/pixel.
    """
    check_halt()
    q = np.pi * np.asarray(diameter, float) * np.asarray(k, float)
    small = np.abs(q) < 0.1  # series: avoids the cancellation of sin q - q cos q
    safe = np.where(small, 1.0, q)
    exact = 3.0 * (np.sin(safe) - safe * np.cos(safe)) / safe**3
    return np.where(small, 1.0 - q**2 / 10.0 + q**4 / 280.0, exact)


def _transfers(freq: np.ndarray, diameters: np.ndarray) -> np.ndarray:
    """:func:`sphere_transfer` on ``freq`` (1, n, m) for each diameter (K,), computed once
    per distinct diameter, shape (K, n, m)."""
    values, inverse = np.unique(diameters, return_inverse=True)
    return sphere_transfer(freq, values[:, None, None])[inverse.reshape(-1)]


def _padded_grid(p: int, extent: float) -> tuple[int, int, np.ndarray]:
    """Padding, FFT size and the radial frequency (cycles / px) of its rfft grid."""
    pad = p // 2 + int(np.ceil(extent)) + 2
    n = sfft.next_fast_len(p + 2 * pad, real=True)
    freq = np.hypot(sfft.fftfreq(n)[:, None], sfft.rfftfreq(n)[None, :])
    return pad, n, freq


def change_size(stack: np.ndarray, d_from, d_to, *, eps: float = 0.1) -> np.ndarray:
    """Re-blur images of spheres of diameter ``d_from`` into spheres of ``d_to``.

    ``F^-1[F(stack) (T(d_to) T(d_from) + eps^2) / (T(d_from)^2 + eps^2)]``: the ratio
    ``T(d_to) / T(d_from)`` where ``|T(d_from)| >> eps``, regularised towards no change
    (gain 1) where ``T(d_from)`` is small (near its zeros no information is left to
    restore, and noise beyond the optics' cutoff is neither amplified nor removed);
    ``d_from = d_to`` is exactly the identity.

    Parameters
    ----------
    stack : ndarray of shape (K, P, P)
        Images centred in their windows (zero-padded here against wrap-around).
    d_from, d_to : float or array_like of shape (K,)
        Diameters in pixels.
    eps : float
        Regularisation of the division by ``T(d_from)``.

    Returns
    -------
    ndarray of shape (K, P, P)
    """
    stack = np.asarray(stack, dtype=np.float64)
    k, p, _ = stack.shape
    d_from = np.broadcast_to(np.asarray(d_from, float), (k,))
    d_to = np.broadcast_to(np.asarray(d_to, float), (k,))
    same = np.isclose(d_from, d_to)
    out = stack.copy()
    todo = np.flatnonzero(~same)
    if len(todo) == 0:
        return out
    pad, n, freq = _padded_grid(p, max(d_from.max(), d_to.max()))
    big = np.zeros((len(todo), n, n))
    big[:, pad:pad + p, pad:pad + p] = stack[todo]
    t_from, t_to = (_transfers(freq[None], d[todo]) for d in (d_from, d_to))
    gain = (t_to * t_from + eps**2) / (t_from**2 + eps**2)
    spec = sfft.rfft2(big, axes=(1, 2)) * gain
    out[todo] = sfft.irfft2(spec, s=(n, n), axes=(1, 2))[:, pad:pad + p, pad:pad + p]
    return out


def _rings(freq: np.ndarray, n: int) -> np.ndarray:
    """Ring index (width ``1 / n`` cycles / px) of each frequency of an rfft grid."""
    return np.round(freq * n).astype(int)


def _ring_profile(values: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Mean of ``values`` (an rfft half-plane) over each ring, shape (rings,)."""
    n = ring.shape[0]
    weights = np.ones_like(values)
    weights[:, 1:-1 if n % 2 == 0 else None] = 2.0  # the rfft half-plane counts twice
    total = np.bincount(ring.ravel(), weights=(values * weights).ravel())
    count = np.bincount(ring.ravel(), weights=weights.ravel())
    return total / np.maximum(count, 1e-300)


def divide_transfer(stack: np.ndarray, transfer, extent: float, *,
                    reference: np.ndarray | None = None, noise: np.ndarray | None = None,
                    max_gain: float | None = MAX_GAIN) -> tuple[np.ndarray, float, float]:
    """Divide a known blur's transfer function out of images, where there is signal.

    With a number for ``max_gain``, the gain at frequency ``k`` is
    ``w(k) / T(k) + (1 - w(k))``, with ``w`` the share of the reference's ring power
    above its noise (see :func:`remove_sphere`) and ``|1 / T|`` capped at ``max_gain``.

    With ``max_gain=None`` the cap is set by the signal, cell by cell: the gain is
    ``(T Q + N) / (T^2 Q + N)``, with ``Q`` the unblurred signal power of the ring
    (fitted to the reference's power above its noise, ``T^2 Q``) and ``N`` the noise
    power. Where ``T^2 Q >> N`` it is ``1 / T``; where the blurred signal sinks into the
    noise (at a zero of ``T``, or beyond the optics' cutoff) it goes to 1, and the image
    is left as it is. Its largest value, about ``sqrt(Q / N) / 2``, grows with the
    signal: a fixed cap limits the result even without noise.

    Parameters
    ----------
    stack : ndarray of shape (I, P, P)
    transfer : callable
        ``transfer(fy, fx) -> T``: the blur's transfer at frequencies in cycles / px
        (arrays of an rfft grid); ``T(0, 0) = 1``.
    extent : float
        The blur's extent in pixels (sets the padding against wrap-around).
    reference, noise
        As in :func:`remove_sphere`.
    max_gain : float or None
        The fixed cap on ``|1 / T|``, or None for the cap set by the signal.

    Returns
    -------
    out : ndarray of shape (I, P, P)
    band : float
        Highest frequency (cycles / px) where at least half the reference's power
        (unblurred, with ``max_gain=None``) is signal.
    max_gain_applied : float
    """
    stack = np.asarray(stack, dtype=np.float64)
    k, p, _ = stack.shape
    ref = stack[0] if reference is None else np.asarray(reference, dtype=np.float64)
    pad, n, freq = _padded_grid(p, extent)
    big = np.zeros((k + 2, n, n))
    big[:k, pad:pad + p, pad:pad + p] = stack
    big[k, pad:pad + p, pad:pad + p] = ref
    if noise is not None:
        big[k + 1, pad:pad + p, pad:pad + p] = noise
    spec = sfft.rfft2(big, axes=(1, 2))
    ring = _rings(freq, n)
    power = np.abs(spec[k]) ** 2
    ring_power = _ring_profile(power, ring)
    if noise is not None:
        noise_power = _ring_profile(np.abs(spec[k + 1]) ** 2, ring)
    else:
        noise_power = float(np.median(power[freq > 0.5])) if np.any(freq > 0.5) else 0.0
    noise_power = np.broadcast_to(np.asarray(noise_power, float), ring_power.shape)
    fy = sfft.fftfreq(n)[:, None] * np.ones((1, freq.shape[1]))
    fx = np.ones((n, 1)) * sfft.rfftfreq(n)[None, :]
    t = np.asarray(transfer(fy, fx), dtype=np.float64)
    if max_gain is None:
        gain, profile = _signal_gain(power, noise_power, ring, t)
    else:
        profile = np.clip(1.0 - noise_power / np.maximum(ring_power, 1e-300), 0.0, 1.0)
        profile[0] = 1.0
        # once the signal has sunk into the noise it stays there (the optics' cutoff):
        # what rises above it further out is not the beads' (re-sampling, window)
        profile = np.minimum.accumulate(profile)
        w = profile[ring]
        inv = np.sign(t) / np.maximum(np.abs(t), 1.0 / max_gain)
        inv = np.where(t == 0, max_gain, inv)
        gain = w * inv + (1.0 - w)
    out = sfft.irfft2(spec[:k] * gain, s=(n, n), axes=(1, 2))[:, pad:pad + p, pad:pad + p]
    signal = freq[profile[ring] >= 0.5]
    band = float(signal.max()) if signal.size else 0.0
    return out, band, float(np.abs(gain).max())


def _signal_gain(power, noise_power, ring, t):
    """The gain ``(T Q + N) / (T^2 Q + N)`` of :func:`divide_transfer` with the cap set
    by the signal, and the share ``Q / (Q + N)`` of each ring. ``Q`` per ring is the
    least-squares fit of ``T^2 Q`` to the reference's power above its noise; once that
    share has fallen to nothing it stays there (the optics' cutoff: what rises further
    out is re-sampling and window, not the beads')."""
    t2 = t * t
    above = np.maximum(power - noise_power[ring], 0.0)
    # per ring: sum(above T^2) / sum(T^4), as ratios of ring means over the same cells
    s = _ring_profile(above * t2, ring) / np.maximum(_ring_profile(t2 * t2, ring), 1e-300)
    nz = np.maximum(noise_power, 1e-12 * max(float(s.max()), 1e-300))
    share = s / (s + nz)
    share[0] = 1.0
    share = np.minimum.accumulate(share)
    s = share / np.maximum(1.0 - share, 1e-12) * nz
    sk, nk = s[ring], nz[ring]
    return (t * sk + nk) / (t2 * sk + nk), share


def remove_sphere(stack: np.ndarray, diameter: float, *, reference: np.ndarray | None = None,
                  noise: np.ndarray | None = None, max_gain: float = MAX_GAIN
                  ) -> tuple[np.ndarray, dict]:
    """Turn images of beads of one known diameter into point-source images.

    A Wiener-type division by the sphere's transfer ``T``, regularised so that noise is
    never amplified where there is no signal to restore: the gain at frequency ``k`` is
    ``w(k) / T(k) + (1 - w(k))`` with ``w = max(0, 1 - N(k) / P(k))`` the fraction of
    the reference's power ``P`` (ring average) above its noise power ``N`` (the ring
    average of ``noise``'s power, or without it the median power beyond Nyquist's
    circle, where a sampled PSF holds little): ``1 / T`` where the
    reference is well above the noise, no change where it is noise alone (beyond the
    optics' cutoff, at the zeros of ``T``); ``|1 / T|`` is capped at ``max_gain``. The
    sum of each image (the zero frequency) is kept.

    Parameters
    ----------
    stack : ndarray of shape (I, P, P)
        Bead images (e.g. a PSF basis), centred in their windows.
    diameter : float
        Bead diameter in pixels (0: returned unchanged).
    reference : ndarray of shape (P, P), optional
        An image of the same beads whose signal-to-noise ratio stands for the stack's
        (e.g. the mean of the normalised bead patches); default ``stack[0]``.
    noise : ndarray of shape (P, P), optional
        An image of the reference's noise alone, e.g. half the difference of the means
        of two halves of the patches (the re-sampling of patches colours their noise, so
        a noise level read off the highest frequencies would be too low).
    max_gain : float
        Largest ``|1 / T|`` applied.

    Returns
    -------
    out : ndarray of shape (I, P, P)
    info : dict
        JSON-ready: ``diameter_px``, ``band_px`` (highest frequency, cycles / px, where
        at least half the reference's power is signal), ``max_gain_applied``,
        ``method``.
    """
    stack = np.asarray(stack, dtype=np.float64)
    diameter = float(diameter)
    if not np.isfinite(diameter) or diameter < 0:
        raise ValueError(f"`bead_diameter` must be finite and >= 0 pixels, got {diameter!r}.")
    info = {"diameter_px": diameter, "method": "sphere transfer divided out where the "
            "signal stands above the noise (Wiener-type, |1/T| capped at "
            f"{max_gain:g}); unchanged where there is noise alone"}
    if diameter == 0 or len(stack) == 0:
        return stack.copy(), {**info, "band_px": None, "max_gain_applied": 1.0}
    out, band, gain_max = divide_transfer(
        stack, lambda fy, fx: sphere_transfer(np.hypot(fy, fx), diameter), diameter,
        reference=reference, noise=noise, max_gain=max_gain)
    info.update(band_px=band, max_gain_applied=gain_max)
    first_zero = FIRST_ZERO_Q / (np.pi * diameter)
    info.update(first_zero_px=float(first_zero))
    if first_zero < band:
        info["warning"] = (
            f"The bead ({diameter:.3g} px) is large for these optics: its transfer "
            f"vanishes at {first_zero:.3g} cycles/px, inside the band the beads show (up "
            f"to {band:.3g}); what the PSF holds near there is lost, and the corrected PSF "
            "is only as good as what is left. Smaller beads calibrate better.")
    return out, info
