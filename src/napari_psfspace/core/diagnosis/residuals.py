"""Honest residuals of a PSF model on beads, on the raw pixels, with a noise model.

For each bead the model's PSF at the bead's position is moved by the bead's sub-pixel
offset (Fourier shift of the model, never an interpolation of the data, so the noise of
the pixels stays independent), then the bead's amplitude ``A`` and a local background
(constant, or a plane) are fitted by weighted least squares on the pixels within the
fit radius, with weights ``1 / var`` from a Poisson-Gaussian :class:`NoiseModel`
(iterated once so that the variance follows the fitted model). Reported per bead:

* ``rel_energy`` = ``||d - model||^2 / ||A m||^2``, the relative residual energy (the
  residual over the fitted pixels, the signal over the whole fit disk, so that masked
  pixels do not inflate it);
* ``chi2`` / ``dof``, with ``dof = n_pixels - n_parameters``;
* ``floor`` = ``sum(var (1 - h)) / ||A m||^2``, ``h`` each pixel's leverage in the
  weighted fit: the relative residual energy a perfect model would leave (noise alone,
  less the share the fitted amplitude, background and companions take up).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np
from scipy import fft as sfft

from ..beads.centering import gather_windows
from ..beads.noise import NoiseModel
from ..beads.window import radial_distance
from ..common.progress import check_halt


@dataclass
class BeadResiduals:
    """Per-bead fits of a model (K beads, patches of size P).

    Attributes
    ----------
    positions : ndarray of shape (K, 2)
    amplitude : ndarray of shape (K,)
        Fitted integrated intensity (ADU, sum of ``A m``).
    background : ndarray of shape (K,)
        Fitted local background at the bead centre (ADU per pixel).
    data, model : ndarray of shape (K, P, P)
        Raw pixels around the rounded bead position, and the fitted model
        (``A m + background``) on them.
    variance : ndarray of shape (K, P, P)
        Noise variance of each pixel under the noise model.
    fit_mask : ndarray of shape (K, P, P), bool
        Pixels used in each bead's fit (within the fit radius, not masked).
    rel_energy, chi2, dof, floor : ndarray of shape (K,)
    """

    positions: np.ndarray
    amplitude: np.ndarray
    background: np.ndarray
    data: np.ndarray
    model: np.ndarray
    variance: np.ndarray
    fit_mask: np.ndarray
    rel_energy: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    floor: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)

    def take(self, index) -> BeadResiduals:
        """The residuals of the beads ``index`` (int array of shape (K',) or bool mask)."""
        return BeadResiduals(*(getattr(self, f.name)[index] for f in fields(self)))

    @classmethod
    def concatenate(cls, parts) -> BeadResiduals:
        """One table of the beads of several (same patch size)."""
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))

    @property
    def residual(self) -> np.ndarray:
        """``data - model`` (K, P, P), zero outside the fit mask."""
        return (self.data - self.model) * self.fit_mask

    @property
    def normalised_residual(self) -> np.ndarray:
        """Residual in noise standard deviations (K, P, P), zero outside the mask."""
        return self.residual / np.sqrt(self.variance)

    def summary(self) -> dict:
        """Totals over beads, JSON-ready: the error of the model.

        ``error`` is the mean over beads of the relative residual energy
        ``||r||^2 / ||A m||^2`` (each bead counts the same: a pooled, signal-weighted
        figure is dominated by the few brightest beads and was measured too noisy to
        decide with) over the informative beads (see :attr:`informative`; ``chi2_dof`` too),
        ``noise_floor`` what noise alone would give, ``chi2_dof`` the
        pooled chi-square per degree of freedom (1 for a model that explains everything
        but the noise), ``error_pooled`` the signal-weighted figure.
        """
        if len(self) == 0:
            return {"n_beads": 0}
        signal = self.rel_energy_denominator
        ok = self.informative
        if not ok.any():
            ok = np.ones(len(self), bool)
        return {
            "n_beads": int(len(self)),
            "n_informative": int(ok.sum()),
            "error": float(np.mean(self.rel_energy[ok])),
            "noise_floor": float(np.mean(self.floor[ok])),
            "chi2_dof": float(np.sum(self.chi2[ok]) / np.sum(self.dof[ok])),
            "error_median": float(np.median(self.rel_energy)),
            "error_pooled": float(np.sum(self.rel_energy * signal) / np.sum(signal)),
        }

    @property
    def informative(self) -> np.ndarray:
        """Beads with a positive fitted amplitude whose noise floor is below 10 % of their
        signal energy, shape (K,).

        A "bead" with almost no fitted signal (a hot pixel taken for a bead, a bead
        under a saturated neighbour) has an unbounded relative residual and carries no
        information on the PSF's shape.
        """
        return (self.floor < 0.1) & (self.amplitude > 0)

    @property
    def photometric(self) -> np.ndarray:
        """Beads whose brightness is measured: a positive fitted amplitude and a noise
        floor below their signal energy, shape (K,).

        Wider than :attr:`informative`: a faint bead on a bright background (floor 0.37:
        its shape says little) still has its amplitude to a few per cent, from all the
        patch's pixels, so it counts for the throughput over the field.
        """
        return (self.floor < 1.0) & (self.amplitude > 0)

    def chi2_under(self, noise: NoiseModel) -> np.ndarray:
        """Per-bead chi-square of these residuals under another noise model, shape (K,)."""
        var = noise.variance(self.model)
        return (((self.data - self.model) ** 2 / var) * self.fit_mask).sum(axis=(1, 2))

    @property
    def rel_energy_denominator(self) -> np.ndarray:
        """``||A m||^2`` per bead over the fit mask, shape (K,)."""
        sig = (self.model - self.background[:, None, None]) * self.fit_mask
        return np.maximum((sig**2).sum(axis=(1, 2)), 1e-300)


def _variance(noise: NoiseModel, mean: np.ndarray, response) -> np.ndarray:
    """Pixel variance at ``mean``; for linearised pixels, the recorded pixels' variance
    divided by the response's squared slope."""
    if response is None:
        return noise.variance(mean)
    return noise.variance(response.forward(mean)) / np.maximum(response.slope(mean), 1e-6) ** 2


def fourier_shift(patches: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Translate each (P, P) patch by (dy, dx) pixels, zero-padded to avoid wrap-around."""
    k, p, _ = patches.shape
    pad = p // 2 + 2
    big = np.pad(patches, ((0, 0), (pad, pad), (pad, pad)))
    n = big.shape[1]
    spec = sfft.rfft2(big, axes=(1, 2))
    ky = sfft.fftfreq(n)[None, :, None]
    kx = sfft.rfftfreq(n)[None, None, :]
    ph = np.exp(-2j * np.pi * (ky * shifts[:, 0, None, None] + kx * shifts[:, 1, None, None]))
    out = sfft.irfft2(spec * ph, s=(n, n), axes=(1, 2))
    return out[:, pad:pad + p, pad:pad + p]


def _companion_models(operator, positions, base, size: int) -> list[np.ndarray]:
    """The model PSF at each companion position, on the patch centred at ``base``."""
    out = []
    for cy, cx in positions:
        psf = operator.psf_at(float(np.clip(cy, 0, operator.image_shape[0] - 1)),
                              float(np.clip(cx, 0, operator.image_shape[1] - 1)))
        shift = np.array([[cy - base[0], cx - base[1]]], dtype=np.float64)
        out.append(fourier_shift(psf[None], shift)[0])
    return out


def fit_beads(
    image,
    positions,
    operator,
    noise: NoiseModel,
    *,
    fit_radius: float | None = None,
    background: str = "constant",
    pixel_mask=None,
    companions: dict | None = None,
    model_filter: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    response=None,
) -> BeadResiduals:
    """Fit amplitude and local background of beads to a model's PSF; measure residuals.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Raw image in ADU (the noise model refers to it).
    positions : array_like of shape (K, 2)
        Sub-pixel bead centres (row, column), as the estimator centres beads.
    operator : ProductConvolution
        The model; ``psf_at`` gives a (P, P) PSF.
    noise : NoiseModel
        Pixel variance as a function of the expected value.
    fit_radius : float, optional
        Pixels within this distance of the patch centre are fitted; default
        ``operator.metadata['psf_radius']`` or ``P // 2``.
    background : {"constant", "plane"}
        Local background model.
    pixel_mask : array_like of shape (M, N), bool, optional
        True for pixels to ignore (hot pixels, saturated pixels, neighbours).
    companions : dict, optional
        ``{(row, col) of a bead (rounded): [(row, col), ...]}``: positions of companion
        beads inside the bead's patch, fitted jointly (one amplitude each, the model's
        PSF at their position); the residual then judges the model, not the crowding.
    model_filter : callable, optional
        ``model_filter(models, positions) -> models``: applied to the beads' model PSFs,
        shape (K, P, P), after the sub-pixel shift, given the bead positions (K, 2);
        e.g. each bead's own size
        (:class:`~napari_psfspace.core.diagnosis.effects.bead_size.SizeFilter`).
    response : object, optional
        For an ``image`` that was linearised (a nonlinear detector): ``response.forward(x)``
        maps linear values back to the recorded ADU, ``response.slope(x)`` is its
        derivative. The fit is made on the linearised pixels with their propagated
        variance; the residuals, chi-square and noise floor are then measured on the
        recorded pixels, under ``noise`` (the recorded image's noise model).

    Returns
    -------
    BeadResiduals
    """
    check_halt()
    img = np.asarray(image, dtype=np.float64)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    p = operator.psf_size
    half = p // 2
    if fit_radius is None:
        fit_radius = float(operator.metadata.get("psf_radius", half))
    if background not in ("constant", "plane"):
        raise ValueError(f"`background` must be 'constant' or 'plane', got {background!r}.")
    mask, base, models, data, excl = _windows(operator, fit_radius, pixel_mask, model_filter, img,
                                              pos, p, half)
    bgc, amp, fitted, var, dof, chi2, leverage = _fit_each(
            operator, noise, background, companions, response, pos, p, mask, base, models, data,
            excl)
    fit_mask = mask[None] & ~excl
    bg_level = bgc[:, None, None]
    if response is not None:  # judge on the recorded pixels
        data, fitted = response.forward(data), response.forward(fitted)
        bg_level = response.forward(bg_level)
        var = noise.variance(np.maximum(fitted, bg_level.min(axis=(1, 2), keepdims=True)))
        chi2 = ((data - fitted) ** 2 / var * fit_mask).sum(axis=(1, 2))
    # the bead's signal energy over the whole fit disk, masked pixels included: masking a
    # saturated core must not make the same residual look relatively larger
    sig = (fitted - bg_level) * mask[None]
    sig2 = np.maximum((sig**2).sum(axis=(1, 2)), 1e-300)
    rel = (((data - fitted) * fit_mask) ** 2).sum(axis=(1, 2)) / sig2
    # what noise alone leaves after the same fit: each pixel's variance less the share
    # the fit takes up (a perfect model's residual; without it the floor stood about 5 %
    # above the held-out error of aberration-free scenes' exact models)
    floor = (var * (1.0 - leverage) * fit_mask).sum(axis=(1, 2)) / sig2
    return BeadResiduals(pos, amp, bgc, data, fitted, var, fit_mask, rel, chi2, dof, floor)


def _windows(operator, fit_radius, pixel_mask, model_filter, img, pos, p, half):
    """The model PSFs shifted to the beads' sub-pixel centres, the data windows, and the
    pixels excluded (masked, or past the image's edge where a window repeats it)."""
    mask = radial_distance(p) <= fit_radius
    base = np.round(pos)
    psfs = np.array([operator.psf_at(y, x) for y, x in pos]) if len(pos) else np.zeros(
        (0, p, p))
    models = fourier_shift(psfs, pos - base)
    if model_filter is not None and len(pos):
        models = model_filter(models, pos)
    data = gather_windows(img, base, half)
    excl = np.zeros_like(data, dtype=bool)
    if pixel_mask is not None:
        excl = gather_windows(np.asarray(pixel_mask, dtype=bool), base, half)
    off = np.arange(-half, half + 1)
    rows, cols_ = base[:, 0, None] + off, base[:, 1, None] + off  # (K, p): past the edge,
    past = ((rows < 0) | (rows > img.shape[0] - 1))[:, :, None] \
        | ((cols_ < 0) | (cols_ > img.shape[1] - 1))[:, None, :]  # a window repeats its edge
    excl = excl | past
    return mask, base, models, data, excl


def _fit_each(operator, noise, background, companions, response, pos, p, mask, base, models, data,
              excl):
    """Each bead's weighted least-squares fit on its fit disk (the model, a constant or
    planar background and its companions), weighted by the data's level and then by the
    fitted model's: the fitted windows, their variance and each pixel's leverage."""
    u = np.linspace(-1.0, 1.0, p)
    yy, xx = np.meshgrid(u, u, indexing="ij")
    n_bg = 1 if background == "constant" else 3
    k = len(pos)
    amp, bgc = np.zeros(k), np.zeros(k)
    fitted = np.zeros_like(data)
    var = np.zeros_like(data)
    chi2, dof = np.zeros(k), np.zeros(k)
    leverage = np.zeros_like(data)
    comp = companions or {}
    for i in range(k):
        use = mask & ~excl[i]
        cols = [models[i][use], np.ones(use.sum())]
        if n_bg == 3:
            cols += [yy[use], xx[use]]
        extra = _companion_models(operator, comp.get(tuple(int(v) for v in base[i]), ()),
                                  base[i], p)
        cols += [e[use] for e in extra]
        design = np.stack(cols, axis=1)
        d = data[i][use]
        v = _variance(noise, np.full_like(d, np.median(d)), response)
        low = float(d.min())
        for _ in range(2):  # weights from the data's level, then from the fitted model
            w = 1.0 / np.sqrt(v)
            coef, *_ = np.linalg.lstsq(design * w[:, None], d * w, rcond=None)
            mod = design @ coef
            # a degenerate fit (negative amplitude) must not drive the variance to its floor
            v = _variance(noise, np.maximum(mod, low), response)
        full = coef[0] * models[i] + coef[1]
        if n_bg == 3:
            full = full + coef[2] * yy + coef[3] * xx
        for c, e in zip(coef[1 + n_bg:], extra, strict=True):
            full = full + c * e
        fitted[i] = full
        # each pixel's leverage in the weighted fit: the share of its noise the fitted
        # amplitude, background and companions take up (the bright core's, mostly)
        xw = design * w[:, None]
        try:
            leverage[i][use] = np.einsum("ij,ij->i", xw, np.linalg.pinv(xw).T)
        except np.linalg.LinAlgError:
            pass
        var[i] = noise.variance(np.maximum(full, low))  # never below the lowest pixel
        amp[i], bgc[i] = coef[0], coef[1]
        chi2[i] = float(np.sum((d - mod) ** 2 / v))
        dof[i] = max(int(use.sum()) - design.shape[1], 1)
    return bgc, amp, fitted, var, dof, chi2, leverage
