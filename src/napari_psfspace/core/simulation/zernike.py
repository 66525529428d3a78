"""Zernike polynomials with Noll's single index and rms normalisation.

Reference: R. J. Noll, "Zernike polynomials and atmospheric turbulence",
J. Opt. Soc. Am. 66 (1976) 207-211.

With this normalisation every polynomial except piston has unit rms over the
unit disk, so a coefficient ``c_j`` is directly the rms wavefront error (in the
unit of ``c_j``, e.g. waves) contributed by mode ``j``:

.. math:: \\frac{1}{\\pi} \\int_{\\rho \\le 1} Z_j Z_k \\, \\rho \\, d\\rho \\, d\\theta
          = \\delta_{jk}.

Noll ordering (``j`` starts at 1): 1 piston, 2 tilt x (cos), 3 tilt y (sin),
4 defocus, 5 oblique astigmatism (sin 2θ), 6 vertical astigmatism (cos 2θ),
7 vertical coma (sin θ), 8 horizontal coma (cos θ), 9/10 trefoil,
11 primary spherical. Even ``j`` carry ``cos(mθ)``, odd ``j`` carry ``sin(mθ)``.
"""

from __future__ import annotations

from math import factorial

import numpy as np

__all__ = ["noll_to_nm", "zernike"]


def noll_to_nm(j: int) -> tuple[int, int]:
    """Convert a Noll index to radial order and signed azimuthal frequency.

    Parameters
    ----------
    j : int
        Noll index, ``j >= 1``.

    Returns
    -------
    n : int
        Radial order, ``n >= 0``.
    m : int
        Signed azimuthal frequency, ``|m| <= n`` and ``n - |m|`` even. ``m > 0``
        means ``cos(m θ)`` (even ``j``), ``m < 0`` means ``sin(|m| θ)`` (odd ``j``).

    Examples
    --------
    >>> [noll_to_nm(j) for j in (1, 4, 5, 6, 11)]
    [(0, 0), (2, 0), (2, -2), (2, 2), (4, 0)]
    """
    j = int(j)
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    p = j - n * (n + 1) // 2  # 1-based position inside row n
    m = 2 * (p // 2) if n % 2 == 0 else 2 * ((p + 1) // 2) - 1
    if m != 0 and j % 2 == 1:
        m = -m
    return n, m


def _radial(n: int, m: int, rho: np.ndarray) -> np.ndarray:
    """Zernike radial polynomial ``R_n^|m|(rho)`` (unnormalised)."""
    m = abs(m)
    out = np.zeros_like(rho, dtype=np.float64)
    for k in range((n - m) // 2 + 1):
        coef = (-1) ** k * factorial(n - k)
        coef /= factorial(k) * factorial((n + m) // 2 - k) * factorial((n - m) // 2 - k)
        out += coef * rho ** (n - 2 * k)
    return out


def zernike(j: int, rho: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Evaluate the rms-normalised Zernike polynomial of Noll index ``j``.

    Parameters
    ----------
    j : int
        Noll index, ``j >= 1``.
    rho : array_like
        Normalised pupil radius, any shape; the polynomial is orthonormal on
        ``rho <= 1``. Values ``rho > 1`` are evaluated as the polynomial
        continuation (no masking; callers mask).
    theta : array_like
        Azimuth in radians, broadcastable with ``rho``; measured from the x
        axis towards the y axis.

    Returns
    -------
    ndarray of float64
        ``Z_j(rho, theta)``, broadcast shape of ``rho`` and ``theta``. Unit rms
        over the unit disk (piston: constant 1).
    """
    n, m = noll_to_nm(j)
    rho, theta = np.broadcast_arrays(np.asarray(rho, float), np.asarray(theta, float))
    radial = _radial(n, m, rho)
    if m == 0:
        return np.sqrt(n + 1.0) * radial
    angular = np.cos(m * theta) if m > 0 else np.sin(-m * theta)
    return np.sqrt(2.0 * (n + 1)) * radial * angular
