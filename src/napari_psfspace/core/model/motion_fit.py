"""The smear's parameters to better than the search's grid: its direction to a tenth of a
degree (:func:`refine_line`, the lowest line of the beads' mean power), then both from
the ``sinc^2`` the smear imprints on that power near its zero line (:func:`fit_line`).

:func:`~napari_psfspace.core.model.motion.detect_motion` finds a zero line on a grid of
directions (:data:`~napari_psfspace.core.model.motion.ANGLE_STEP`) and frequency bins; the
division of the smear (:func:`~napari_psfspace.core.model.motion.remove_motion`) is only
as good as those two numbers.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft
from scipy import ndimage as ndi

#: The zero line found on the search's grid (:data:`ANGLE_STEP`, one frequency bin) is
#: refined within this many degrees and this fraction of its frequency ...
REFINE_ANGLE = 2.5
REFINE_FREQUENCY = 0.15
#: ... in steps of this many degrees and this fraction of its frequency.
REFINE_STEPS = (0.1, 0.0025)


def refine_line(power: np.ndarray, ring_mean: np.ndarray, n: int, angle: float, t0: float,
                 width: float, band: float) -> tuple[float, float]:
    """The zero line ``k.u = t`` of a smear, to a tenth of a degree and a fraction of a
    frequency bin: the line, among those near ``(angle, t0)``, along which the beads'
    mean power (over its mean over directions at each radius, ``ring_mean``, so that the
    optics' fall with frequency does not pull it outwards) is lowest, sampled by
    bilinear interpolation over ``|k.u_perp| < width`` inside the band. A smear's
    transfer vanishes on the whole line, so a line tilted or shifted off it rises on
    both sides: the minimum is the smear's direction and ``1 / length``."""
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = sfft.fftshift(np.where(ring_mean > 0, power / ring_mean, np.nan))
    rel = np.nan_to_num(rel, nan=np.nanmax(rel) if np.isfinite(rel).any() else 0.0)
    s = np.linspace(-width, width, 41)
    ts = t0 * (1.0 + np.arange(-REFINE_FREQUENCY, REFINE_FREQUENCY + 1e-9, REFINE_STEPS[1]))
    best = (np.inf, angle, t0)
    for ang in angle + np.arange(-REFINE_ANGLE, REFINE_ANGLE + 1e-9, REFINE_STEPS[0]):
        a = np.deg2rad(ang)
        ky = ts[:, None] * np.sin(a) - s[None, :] * np.cos(a)
        kx = ts[:, None] * np.cos(a) + s[None, :] * np.sin(a)
        inside = np.hypot(ky, kx) <= band
        vals = ndi.map_coordinates(rel, [ky.ravel() * n + n // 2, kx.ravel() * n + n // 2],
                                   order=1, mode="nearest").reshape(ky.shape)
        vals = np.log(np.maximum(vals, 1e-6))
        mean = np.where(inside, vals, 0.0).sum(axis=1) / np.maximum(inside.sum(axis=1), 1)
        mean[inside.sum(axis=1) < 5] = np.inf
        i = int(np.argmin(mean))
        if mean[i] < best[0]:
            best = (float(mean[i]), float(ang) % 180.0, float(ts[i]))
    return best[1], best[2]


#: The zero line's frequency is searched within this many frequency bins (``1 / n``) of
#: the bin where it was found (the search's own precision: further off, the fit would
#: trust the optics' shape over the zero) and the direction within this many degrees ...
LENGTH_SPAN = 1.5
ANGLE_SPAN = 3.0
#: ... first on a coarse grid (a twentieth of a bin, a quarter of a degree), then around
#: its best point on a fine one (a tenth of that, a fiftieth of a degree).
COARSE_STEPS = (0.05, 0.25)
FINE_STEPS = (0.005, 0.02)
#: Only the cells within this fraction of the zero line's frequency from it are fitted.
ZERO_REACH = 0.4


def fit_line(power: np.ndarray, var: np.ndarray, n: int, angle: float, t0: float,
             band: float) -> tuple[float, float]:
    """The smear's direction and length from the ``sinc^2`` it imprints on the beads'
    mean power.

    Model: ``P(k) = O(|k|) sinc^2(L k.u)`` inside the band and within
    :data:`ZERO_REACH` of the zero line, with ``O`` any radial function (the optics,
    averaged over the field) and ``u`` the smear's direction. For each trial ``(u, L)``
    the best ``O`` of each ring is its least-squares value; the pair kept is the one
    whose residual, each ring weighted by its noise variance, is lowest. Near the zero
    the ``sinc^2`` sets the shape; further from it the optics' own departure from a
    radial function (the field's astigmatism, averaged) pulls the length, which is why
    the fit stays there, and within :data:`LENGTH_SPAN` bins of the line's own
    frequency (``bench/bench_motion.py``).

    Parameters
    ----------
    power : ndarray of shape (n, n)
        Mean signal power of the beads (noise removed), on the full ``fftfreq(n)`` grid.
    var : ndarray of shape (n, n)
        Its variance, cell by cell.
    n : int
        Grid size.
    angle : float
        Direction of the zero line found, degrees (as
        :class:`~napari_psfspace.core.model.motion.Motion`).
    t0 : float
        Its frequency, cycles / px.
    band : float
        Highest frequency where the beads' signal is seen, cycles / px.

    Returns
    -------
    angle : float
        Degrees in [0, 180), within :data:`ANGLE_SPAN` of ``angle``.
    length : float
        Pixels: ``1 / t`` with ``t`` within :data:`LENGTH_SPAN` bins of ``t0``.
    """
    f = sfft.fftfreq(n)
    fy, fx = f[:, None] * np.ones((1, n)), np.ones((n, 1)) * f[None, :]
    rad = np.hypot(fy, fx)
    a0 = np.deg2rad(angle)
    near = np.abs(np.abs(fy * np.sin(a0) + fx * np.cos(a0)) / t0 - 1.0) <= ZERO_REACH
    inside = (rad <= band) & (rad > 0) & near
    if np.count_nonzero(inside) < 8:  # nothing to fit: the line as found
        return angle % 180.0, 1.0 / t0
    ring = np.round(rad[inside] * n).astype(int)
    ky, kx, s = fy[inside], fx[inside], power[inside]
    nr = int(ring.max()) + 1
    cnt = np.maximum(np.bincount(ring, minlength=nr), 1)
    v = np.bincount(ring, weights=var[inside], minlength=nr) / cnt
    w = 1.0 / np.maximum(v, 1e-300 + 1e-12 * float(np.max(v)))

    def score(ang, length):
        a = np.deg2rad(ang)
        m = np.sinc(length * (ky * np.sin(a) + kx * np.cos(a))) ** 2
        num = np.bincount(ring, weights=s * m, minlength=nr)
        den = np.bincount(ring, weights=m * m, minlength=nr)
        return float(np.sum(w * num**2 / np.maximum(den, 1e-300)))

    def search(angles, lengths):
        best = (-np.inf, angle, 1.0 / t0)
        for ang in angles:
            for length in lengths:
                g = score(ang, length)
                if g > best[0]:
                    best = (g, float(ang), float(length))
        return best[1], best[2]

    bins = np.arange(-LENGTH_SPAN, LENGTH_SPAN + 1e-9, COARSE_STEPS[0])
    ang, length = search(angle + np.arange(-ANGLE_SPAN, ANGLE_SPAN + 1e-9, COARSE_STEPS[1]),
                         1.0 / (t0 + bins / n))
    t1 = 1.0 / length
    fine_b = np.arange(-COARSE_STEPS[0], COARSE_STEPS[0] + 1e-9, FINE_STEPS[0])
    fine_b = fine_b[np.abs((t1 - t0) * n + fine_b) <= LENGTH_SPAN]
    fine_a = np.arange(-COARSE_STEPS[1], COARSE_STEPS[1] + 1e-9, FINE_STEPS[1])
    ang, length = search(ang + fine_a, 1.0 / (t1 + fine_b / n))
    return ang % 180.0, length
