"""Least-squares Gaussians with an offset: the profile a microscopist's FWHM is read from.

napari-psf-analysis and PSF-Extractor quote a bead's FWHM from a Gaussian fitted with a
constant offset (the background, and the rings and wings a Gaussian cannot follow): a
1-D Gaussian along the axial profile through the bead's centre, a 2-D Gaussian with a
full covariance (an ellipse at any angle) on the plane in focus. The same models are fitted
here, by Levenberg-Marquardt with analytic Jacobians (:func:`scipy.optimize.least_squares`).

* :func:`fit_gaussian_1d`: ``b + a exp(-(x - mu)^2 / (2 sigma^2))``;
* :func:`fit_gaussian_2d`: ``b + a exp(-d^T C^{-1} d / 2)``, ``d`` the offset from the
  centre ``(y, x)``, ``C`` the 2 x 2 covariance (pixels^2), parameterised by its inverse
  so that the model is smooth in every parameter.

A fit that does not converge, whose amplitude is not positive, whose covariance is not
positive definite, or whose centre leaves the data is returned with ``ok = False`` and NaN
widths: the caller decides, nothing raises.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from scipy.optimize import least_squares

#: A Gaussian's full width at half maximum over its standard deviation.
FWHM_PER_SIGMA = float(2.0 * np.sqrt(2.0 * np.log(2.0)))


@dataclass(frozen=True)
class Gaussian1D:
    """A 1-D Gaussian with an offset (samples as the unit of length).

    Attributes
    ----------
    background, amplitude, centre, sigma : float
    ok : bool
        The fit converged to a positive peak within the profile.
    """

    background: float
    amplitude: float
    centre: float
    sigma: float
    ok: bool

    @property
    def fwhm(self) -> float:
        """Full width at half maximum, samples (NaN when the fit failed)."""
        return FWHM_PER_SIGMA * self.sigma if self.ok else float("nan")


@dataclass(frozen=True)
class Gaussian2D:
    """An elliptical 2-D Gaussian with an offset (pixels as the unit of length).

    Attributes
    ----------
    background, amplitude : float
    centre : tuple of float
        ``(row, column)`` in the plane's pixel coordinates.
    covariance : ndarray of shape (2, 2)
        Rows first: ``[[c_rr, c_rc], [c_rc, c_cc]]``, pixels^2.
    ok : bool
        The fit converged to a positive peak, a positive definite covariance and a
        centre inside the plane.
    """

    background: float
    amplitude: float
    centre: tuple[float, float]
    covariance: np.ndarray
    ok: bool

    def _nan_unless_ok(self, value: float) -> float:
        return float(value) if self.ok else float("nan")

    @property
    def fwhm_row(self) -> float:
        """FWHM along the rows (the y axis), pixels."""
        return self._nan_unless_ok(FWHM_PER_SIGMA * np.sqrt(max(self.covariance[0, 0], 0.0)))

    @property
    def fwhm_col(self) -> float:
        """FWHM along the columns (the x axis), pixels."""
        return self._nan_unless_ok(FWHM_PER_SIGMA * np.sqrt(max(self.covariance[1, 1], 0.0)))

    @property
    def principal(self) -> tuple[float, float, float]:
        """``(fwhm_major, fwhm_minor, angle)``: the FWHM along the ellipse's principal
        axes (pixels, major first) and the major axis' angle from the row axis towards
        the column axis (radians, in ``(-pi/2, pi/2]``)."""
        if not self.ok:
            return float("nan"), float("nan"), float("nan")
        w, v = np.linalg.eigh(self.covariance)
        major, minor = FWHM_PER_SIGMA * np.sqrt(np.clip(w[::-1], 0.0, None))
        angle = float(np.arctan2(v[1, 1], v[0, 1]))
        if angle <= -np.pi / 2:
            angle += np.pi
        elif angle > np.pi / 2:
            angle -= np.pi
        return float(major), float(minor), angle


def _check_finite(values: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"`{name}` must be finite, got {int((~np.isfinite(arr)).sum())} "
                         "NaN or infinite value(s).")
    return arr


def fit_gaussian_1d(profile, positions=None, *, offset: bool = True) -> Gaussian1D:
    """Fit ``b + a exp(-(x - mu)^2 / (2 sigma^2))`` to a profile.

    Parameters
    ----------
    profile : array_like of shape (N,)
        The samples, N >= 4.
    positions : array_like of shape (N,), optional
        Where each sample lies (default ``0 .. N-1``), increasing.
    offset : bool
        Fit the offset ``b``; False holds it at 0 (a background-free profile too short
        to show its own floor).

    Returns
    -------
    Gaussian1D
        In the units of ``positions``.
    """
    y = _check_finite(profile, "profile").ravel()
    n = len(y)
    if n < 4:
        raise ValueError(f"`profile` must hold at least 4 samples, got {n}.")
    x = np.arange(n, dtype=np.float64) if positions is None else _check_finite(
        positions, "positions").ravel()
    if len(x) != n:
        raise ValueError(f"`positions` must have the profile's length {n}, got {len(x)}.")
    step = float(np.median(np.diff(x))) if n > 1 else 1.0
    bg0 = float(min(y[0], y[-1], np.percentile(y, 10))) if offset else 0.0
    k = int(np.argmax(y))
    amp0 = float(y[k] - bg0)
    if amp0 <= 0:
        return Gaussian1D(bg0, 0.0, float(x[k]), float("nan"), False)
    above = y - bg0 >= amp0 / 2
    sig0 = max(float(above.sum()) * abs(step) / FWHM_PER_SIGMA, 0.5 * abs(step))

    def resid(p):
        b, a, mu, s = p
        return b + a * np.exp(-0.5 * ((x - mu) / s) ** 2) - y

    def jac(p):
        b, a, mu, s = p
        t = (x - mu) / s
        g = np.exp(-0.5 * t * t)
        return np.stack([np.ones_like(x), g, a * g * t / s, a * g * t * t / s], axis=1)

    scale = max(abs(amp0), 1e-300)
    free = slice(0, 4) if offset else slice(1, 4)  # the offset held at 0: three parameters

    def full(q):
        return np.concatenate([[0.0], q]) if not offset else q

    try:
        res = least_squares(lambda q: resid(full(q)) / scale,
                            [bg0, amp0, float(x[k]), sig0][free],
                            jac=lambda q: jac(full(q))[:, free] / scale, method="lm",
                            max_nfev=200)
        b, a, mu, s = full(res.x)
        ok = bool(res.success) and a > 0 and abs(s) > 0 and x.min() <= mu <= x.max()
    except (ValueError, np.linalg.LinAlgError):
        b, a, mu, s, ok = bg0, amp0, float(x[k]), sig0, False
    return Gaussian1D(float(b), float(a), float(mu), float(abs(s)) if ok else float("nan"),
                      bool(ok))


def _moment_guess(plane: np.ndarray, bg: float) -> tuple[float, float, float, float, float]:
    """Peak (3 x 3 mean), centre and second moments of the light above ``bg`` near the
    peak: the Levenberg-Marquardt start."""
    sm = ndi.uniform_filter(plane, 3, mode="nearest")
    py, px = np.unravel_index(int(np.argmax(sm)), plane.shape)
    amp = float(sm[py, px] - bg)
    a = np.clip(plane - bg, 0.0, None)
    above = a >= amp / 2
    r = max(2.0, 1.5 * np.sqrt(max(above.sum(), 1) / np.pi))
    yy, xx = np.indices(plane.shape, dtype=np.float64)
    m = a * ((yy - py) ** 2 + (xx - px) ** 2 <= r * r)
    tot = m.sum()
    if tot <= 0:
        return amp, float(py), float(px), 1.0, 1.0
    cy, cx = float((m * yy).sum() / tot), float((m * xx).sum() / tot)
    # the core's half-maximum area gives the width: moments within r of a Gaussian
    # truncated at 1.5 half-widths underestimate it
    s2 = max(float(above.sum()) / np.pi / (FWHM_PER_SIGMA / 2) ** 2, 0.25)
    return amp, cy, cx, s2, s2


def fit_gaussian_2d(plane, *, centre: tuple[float, float] | None = None,
                    radius: float | None = None) -> Gaussian2D:
    """Fit an elliptical Gaussian with an offset to a plane.

    Parameters
    ----------
    plane : array_like of shape (M, N)
        One plane of a PSF or a bead patch, M, N >= 5.
    centre : (float, float), optional
        Where to fit, ``(row, column)``: with ``radius``, only the pixels within
        ``radius`` of it are fitted (default: the whole plane).
    radius : float, optional
        Radius of the fitted disk, pixels.

    Returns
    -------
    Gaussian2D
        Centre in the plane's pixel coordinates, covariance in pixels^2.
    """
    img = _check_finite(plane, "plane")
    if img.ndim != 2 or min(img.shape) < 5:
        raise ValueError(f"`plane` must be 2-D, at least 5 x 5, got shape {img.shape}.")
    yy, xx = np.indices(img.shape, dtype=np.float64)
    mask = np.ones(img.shape, bool)
    if radius is not None:
        cy0, cx0 = ((img.shape[0] - 1) / 2, (img.shape[1] - 1) / 2) if centre is None \
            else centre
        mask = (yy - cy0) ** 2 + (xx - cx0) ** 2 <= float(radius) ** 2
    border = np.concatenate([img[0], img[-1], img[1:-1, 0], img[1:-1, -1]])
    bg0 = float(np.median(border))
    amp0, cy, cx, syy, sxx = _moment_guess(np.where(mask, img, bg0), bg0)
    nan = np.full((2, 2), np.nan)
    if amp0 <= 0:
        return Gaussian2D(bg0, 0.0, (cy, cx), nan, False)
    y, x, v = yy[mask], xx[mask], img[mask]
    scale = amp0

    def parts(p):
        b, a, my, mx, ia, ib, ic = p
        dy, dx = y - my, x - mx
        g = np.exp(-0.5 * (ia * dy * dy + 2 * ib * dy * dx + ic * dx * dx))
        return b, a, dy, dx, ia, ib, ic, g

    def resid(p):
        b, a, *_, g = parts(p)
        return (b + a * g - v) / scale

    def jac(p):
        b, a, dy, dx, ia, ib, ic, g = parts(p)
        ag = a * g
        return np.stack([np.ones_like(g), g, ag * (ia * dy + ib * dx), ag * (ib * dy + ic * dx),
                         -0.5 * ag * dy * dy, -ag * dy * dx, -0.5 * ag * dx * dx],
                        axis=1) / scale

    p0 = [bg0, amp0, cy, cx, 1.0 / syy, 0.0, 1.0 / sxx]
    try:
        res = least_squares(resid, p0, jac=jac, method="lm", max_nfev=300)
        b, a, my, mx, ia, ib, ic = res.x
        det = ia * ic - ib * ib
        ok = (bool(res.success) and a > 0 and ia > 0 and det > 0
              and 0 <= my <= img.shape[0] - 1 and 0 <= mx <= img.shape[1] - 1)
        cov = np.array([[ic, -ib], [-ib, ia]]) / det if det > 0 else nan
    except (ValueError, np.linalg.LinAlgError):
        b, a, my, mx, cov, ok = bg0, amp0, cy, cx, nan, False
    return Gaussian2D(float(b), float(a), (float(my), float(mx)),
                      cov if ok else nan, bool(ok))


__all__ = ["FWHM_PER_SIGMA", "Gaussian1D", "Gaussian2D", "fit_gaussian_1d", "fit_gaussian_2d"]
