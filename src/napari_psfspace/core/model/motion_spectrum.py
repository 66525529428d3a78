"""The beads' mean power spectrum, as :func:`~.motion.detect_motion` reads it.

The noise-weighted mean of the beads' signal power ``|F p|^2 - N`` on a fine grid (a
zero line is narrow), kept in eight parts: the field's four quarters (by the beads'
positions) times two halves of the beads. The halves' difference estimates the noise of
the mean power, ring by ring; the band is where the mean stands clear of it. Inside the
band, the spectrum is read along strips in every direction: each strip's profile over
the mean of all directions cancels a lens's fall towards its cutoff and the knee at the
band's edge, but not a smear's zero line.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

#: The band where the beads' mean signal power exceeds this many standard errors ...
BAND_Z = 5.0
#: ... and this fraction of its zero-frequency value: beyond the optics' cutoff the mean
#: power of windowed, re-sampled patches sits on a floor of ~1e-4 (interpolation, window
#: leakage, background errors) that is measured precisely but is not the beads' signal;
#: the knee where the spectrum meets it would read as a dip.
BAND_FLOOR = 1e-4


class BeadSpectrum:
    """The mean power spectrum of bead patches, its band and its strip profiles.

    Parameters
    ----------
    psf : ndarray of shape (K, P, P)
        Sum-1 windowed bead patches.
    noise : ndarray of shape (K,)
        Each patch's noise power per frequency.
    group : ndarray of shape (K,), int
        Each bead's quarter of the field, 0-3.
    n : int
        Side of the Fourier grid, bins.
    """

    def __init__(self, psf: np.ndarray, noise: np.ndarray, group: np.ndarray, n: int):
        half = np.arange(len(psf)) % 2  # two halves estimate the noise of the mean power
        labels = group * 2 + half  # quarter (0-3) x half (0-1)
        self.n, self.group = n, group
        self.parts = mean_powers(psf, noise, n, labels, 8)
        self.weights = np.bincount(labels, weights=1.0 / np.maximum(noise, 1e-300),
                                   minlength=8)
        f = sfft.fftfreq(n)
        self.fy, self.fx = f[:, None] * np.ones((1, n)), np.ones((n, 1)) * f[None, :]
        rad = np.hypot(self.fy, self.fx)
        self.mean = self.combine(np.arange(8))
        # standard error of the mean power, from two halves of the beads
        diff = self.combine(np.arange(0, 8, 2)) - self.combine(np.arange(1, 8, 2))
        ring = np.round(rad * n).astype(int)
        ring_var = (np.bincount(ring.ravel(), weights=(diff**2 / 4).ravel())
                    / np.maximum(np.bincount(ring.ravel()), 1))
        ring_mean = np.bincount(ring.ravel(), weights=self.mean.ravel()) / np.maximum(
            np.bincount(ring.ravel()), 1)
        seen = ((ring_mean > BAND_Z * np.sqrt(ring_var / np.maximum(np.bincount(ring.ravel()),
                                                                     1)))
                & (ring_mean > BAND_FLOOR * ring_mean[0]))
        seen[0] = True
        last = int(np.argmin(seen)) - 1 if not seen.all() else len(seen) - 1
        #: The band's edge, cycles / px.
        self.band = max(last, 1) / n
        #: The mean power's variance and its mean over each ring, on the grid.
        self.var_map, self.ring_mean = ring_var[ring], ring_mean[ring]
        self.inside = rad <= self.band

    def combine(self, sel) -> np.ndarray:
        """The weighted mean of the parts ``sel``, shape (n, n)."""
        ws = self.weights[sel]
        return np.einsum("g,gij->ij", ws, self.parts[sel]) / max(ws.sum(), 1e-300)

    def set_strips(self, angles: np.ndarray, width: float) -> None:
        """For every direction of ``angles`` (degrees): the cells of the strip
        ``|k.u_perp| < width`` inside the band and their bin of ``|k.u|``, computed once
        and used for every spectrum; the bins' ``centres`` and each bin's cell count."""
        n, band = self.n, self.band
        edges = (np.arange(int(np.ceil(band * n)) + 2) - 0.5) / n
        self.centres = 0.5 * (edges[1:] + edges[:-1])
        nb = len(self.centres)
        flat_inside = np.flatnonzero(self.inside.ravel())
        fyi, fxi = self.fy.ravel()[flat_inside], self.fx.ravel()[flat_inside]
        self.geometry = []
        for ang in angles:
            a = np.deg2rad(ang)
            t = np.abs(fyi * np.sin(a) + fxi * np.cos(a))
            s_ = np.abs(-fyi * np.cos(a) + fxi * np.sin(a))
            idx = np.digitize(t, edges) - 1
            ok = (s_ < width) & (idx >= 0) & (idx < nb)
            self.geometry.append((flat_inside[ok], idx[ok],
                                  np.bincount(idx[ok], minlength=nb).astype(float)))
        self.counts = self.geometry[0][2]

    def strip_profiles(self, spec: np.ndarray) -> np.ndarray:
        """The mean of ``spec`` over each strip's bins, shape (angles, bins)."""
        v = spec.ravel()
        nb = len(self.centres)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.array([np.bincount(b_, weights=v[c_], minlength=nb) / n_
                             for c_, b_, n_ in self.geometry])

    def profiles(self, spec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Strip profile along every direction over the mean of all directions (shape
        (angles, bins)), and that mean."""
        prof = self.strip_profiles(spec)
        finite = np.isfinite(prof)
        ref = np.where(finite, prof, 0.0).sum(axis=0) / np.maximum(finite.sum(axis=0), 1)
        ref[~finite.any(axis=0)] = np.nan
        with np.errstate(invalid="ignore", divide="ignore"):
            return prof / ref, ref

    def quarter_profiles(self, g: int) -> np.ndarray:
        """:meth:`profiles` of the beads of quarter ``g`` alone."""
        return self.profiles(self.combine(np.array([2 * g, 2 * g + 1])))[0]


def mean_powers(psf: np.ndarray, noise: np.ndarray, n: int, labels: np.ndarray,
                n_labels: int, chunk: int = 32) -> np.ndarray:
    """Noise-weighted mean signal power ``|F p|^2 - N`` of the beads of each label, on
    an ``n x n`` grid, shape (n_labels, n, n) (zero for a label without beads);
    computed in chunks of beads, so that memory does not grow with their number."""
    k, p, _ = psf.shape
    w = 1.0 / np.maximum(noise, 1e-300)
    n_lab = int(n_labels)
    wsum = np.bincount(labels, weights=w, minlength=n_lab)
    big = np.zeros((min(chunk, k), n, n))
    tot = np.zeros((n_lab, n, n // 2 + 1))
    for start in range(0, k, chunk):
        m = min(chunk, k - start)
        big[:m, :p, :p] = psf[start:start + m]  # the phase does not matter: powers only
        power = np.abs(sfft.rfft2(big[:m], axes=(1, 2), workers=2)) ** 2
        power -= noise[start:start + m, None, None]
        power *= w[start:start + m, None, None]
        for lab in np.unique(labels[start:start + m]):
            tot[lab] += power[labels[start:start + m] == lab].sum(axis=0)
    half = tot / np.maximum(wsum, 1e-300)[:, None, None]
    # the power of a real image is even: P(-k) = P(k) fills the other half-plane
    full = np.empty((n_lab, n, n))
    full[:, :, :n // 2 + 1] = half
    cols = np.arange(n // 2 + 1, n)
    full[:, :, cols] = half[:, (-np.arange(n)) % n][:, :, n - cols]
    return full
