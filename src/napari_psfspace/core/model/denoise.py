"""Use each bead by its information: noise-aware learning of the PSF basis and field.

At low signal per pixel most of a patch's pixels carry noise only: the PSF lives in a
small part of the Fourier plane (inside the optical cutoff, and mostly at low
frequencies), while white noise fills all of it. Two steps, both linear and measured in
``bench/bench_accuracy.py`` (noise-level table):

1. :func:`band_limit` filters every patch with one Wiener filter ``S / (S + N)``: ``S``
   is the mean signal power of the patches (their power minus their noise power), ``N``
   the noise power of a typical bead. The same filter for every bead keeps the basis
   free of a bead-dependent blur; the PCA then sees the PSFs' variation rather than
   noise (the noise fills far fewer dimensions).
2. :func:`refit_basis` fits the basis images again to the *unfiltered* patches, given
   the smooth coefficient field at the beads (weighted least squares over all beads at
   once, PSFEx-style), then shrinks each basis image by its own Wiener filter from its
   own noise (which is that of an average over all beads, far below a bead's). The
   filter of step 1 no longer biases the model, and the noise that is left is that of
   the whole set of beads.

Both are off-switchable (``denoise=False`` in
:func:`~napari_psfspace.core.model.estimate.estimate_operator`) and record what they did.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

#: The learning filter is set for the bead at this quantile of the noise power (the
#: median bead): fainter beads are under-filtered, brighter ones over-filtered; their
#: weights (``1 / ||p||^2`` of the raw patch, noise included) do the rest.
NOISE_QUANTILE = 0.5

#: Ridge of the refit towards the prior basis, relative to the largest eigenvalue of
#: ``A^T W A``: smooth coefficient fields can be nearly collinear (several of them close
#: to affine), and the directions they do not determine keep the prior's images.
RIDGE = 1e-2


def patch_noise(noise_sd: np.ndarray, window: np.ndarray) -> np.ndarray:
    """Expected noise power per Fourier coefficient of each windowed sum-1 patch.

    Parameters
    ----------
    noise_sd : ndarray of shape (K,)
        Per-pixel noise standard deviation of each sum-1 patch (the image
        noise divided by the bead's flux).
    window : ndarray of shape (P, P)
        The window the patches were multiplied by.

    Returns
    -------
    ndarray of shape (K,)
        ``sigma_m^2 sum(window^2)``: white noise's power at every frequency.
    """
    return np.asarray(noise_sd, dtype=np.float64) ** 2 * float((window**2).sum())


def _whole_plane(half: np.ndarray, width: int) -> np.ndarray:
    """A power spectrum (P, width) of real patches from its half plane (P, width // 2 +
    1, ``rfft2``'s): ``|F(-k)| = |F(k)|``."""
    rows, m = half.shape
    out = np.empty((rows, width))
    out[:, :m] = half
    cols = np.arange(m, width)
    out[:, cols] = half[(-np.arange(rows)) % rows][:, width - cols]
    return out


def signal_power(power: np.ndarray, noise: np.ndarray, width: int | None = None
                 ) -> np.ndarray:
    """Mean signal power of the patches, shape (P, P), from their power spectra
    ``|F p_m|^2`` (K, P, P; or, with the patches' ``width``, their half plane of
    ``rfft2``, (K, P, width // 2 + 1)): noise-weighted mean of ``|F p_m|^2 - N_m``,
    smoothed over 3 x 3 frequencies and clipped at 0."""
    w = 1.0 / np.maximum(noise, 1e-300)
    mean = np.einsum("k,kij->ij", w, power - noise[:, None, None]) / w.sum()
    if width is not None:
        mean = _whole_plane(mean, int(width))
    return np.maximum(ndi.uniform_filter(mean, 3, mode="wrap"), 0.0)


def band_limit(psf: np.ndarray, noise_sd: np.ndarray,
               window: np.ndarray) -> tuple[np.ndarray, dict]:
    """One Wiener filter for all patches: ``S / (S + N_typical)``.

    Parameters
    ----------
    psf : ndarray of shape (K, P, P)
        Sum-1 windowed patches.
    noise_sd : ndarray of shape (K,)
        Per-pixel noise of each patch (image noise / flux).
    window : ndarray of shape (P, P)

    Returns
    -------
    filtered : ndarray of shape (K, P, P)
    info : dict
        ``passband``: share of the Fourier plane where the filter exceeds 1/2;
        ``noise_power``: the typical bead's noise power per coefficient.
    """
    psf = np.asarray(psf, dtype=np.float64)
    noise = patch_noise(noise_sd, window)
    # the patches are real: half the plane's spectra (rfft2), half the transforms' cost;
    # the power on the whole plane (for the smoothing, which wraps) from its symmetry
    spectra = np.fft.rfft2(psf)  # (K, P, P // 2 + 1)
    s = signal_power(spectra.real ** 2 + spectra.imag ** 2, noise, psf.shape[-1])
    n_typ = float(np.quantile(noise, NOISE_QUANTILE))
    gain = s / (s + n_typ) if n_typ > 0 else np.ones_like(s)
    out = np.fft.irfft2(spectra * gain[None, :, :spectra.shape[-1]], s=psf.shape[-2:])
    return out, {"passband": float(np.mean(gain > 0.5)), "noise_power": n_typ}


def refit_basis(
    psf: np.ndarray,
    coefficients: np.ndarray,
    noise_sd: np.ndarray,
    window: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    prior: np.ndarray | None = None,
    shrink: bool = True,
) -> tuple[np.ndarray, dict]:
    """Basis images refitted to raw patches given their (smooth) coefficients.

    Minimises ``sum_m w_m ||p_m - sum_i a_{m,i} h_i||^2 + lambda ||h - h_prior||^2``
    over the images ``h_i`` (a
    weighted least-squares regression of every pixel on the coefficients), then shrinks
    each ``h_i`` by the Wiener filter of its own noise: ``Cov(h) = G^-1 (A^T W V W A)
    G^-1`` with ``G = A^T W A`` and ``V`` the beads' noise variances.

    Parameters
    ----------
    psf : ndarray of shape (K, P, P)
        Unfiltered sum-1 patches.
    coefficients : ndarray of shape (K, I)
        Coefficients ``a_{m,i}`` of each bead (the fitted field at the bead).
    noise_sd : ndarray of shape (K,)
        Per-pixel noise of each patch.
    window : ndarray of shape (P, P)
    weights : ndarray of shape (K,), optional
        Weights ``w_m`` (default ``1 / ||p_m||^2``).
    prior : ndarray of shape (I, P, P), optional
        Images the refit is drawn towards (ridge ``RIDGE * max eig(A^T W A)``) where the
        coefficients do not determine it, e.g. the PCA basis; default: none (plain
        weighted least squares).
    shrink : bool
        Apply the per-image Wiener shrinkage.

    Returns
    -------
    basis : ndarray of shape (I, P, P)
    info : dict
        ``noise_rel``: each image's noise norm relative to its norm before shrinkage.
    """
    psf = np.asarray(psf, dtype=np.float64)
    k, p, _ = psf.shape
    a = np.asarray(coefficients, dtype=np.float64).reshape(k, -1)
    y = psf.reshape(k, -1)
    w = 1.0 / np.maximum((y**2).sum(axis=1), 1e-300) if weights is None else np.asarray(weights)
    aw = a.T * w  # (I, K)
    g = aw @ a
    n_i = g.shape[0]
    if prior is None:  # plain weighted least squares
        h0, lam = np.zeros((n_i, p * p)), 0.0
    else:
        h0 = np.asarray(prior, float).reshape(n_i, -1)
        lam = RIDGE * float(np.linalg.eigvalsh(g).max())
    ginv = np.linalg.pinv(g + lam * np.eye(n_i))
    h = (ginv @ (aw @ y + lam * h0)).reshape(-1, p, p)
    var = np.asarray(noise_sd, dtype=np.float64) ** 2
    cov = ginv @ ((aw * var) @ aw.T) @ ginv  # noise covariance of h per pixel
    noise = np.clip(np.diag(cov), 0, None) * float((window**2).sum())  # per coefficient
    rel = np.sqrt(noise) / np.maximum(np.linalg.norm(h.reshape(len(h), -1), axis=1), 1e-300)
    if shrink:
        spectra = np.fft.fft2(h)
        for i in range(len(h)):
            s = np.maximum(ndi.uniform_filter(np.abs(spectra[i]) ** 2 - noise[i], 3,
                                              mode="wrap"), 0.0)
            gain = s / (s + noise[i]) if noise[i] > 0 else 1.0
            h[i] = np.real(np.fft.ifft2(spectra[i] * gain))
    return h, {"noise_rel": [float(v) for v in rel]}
