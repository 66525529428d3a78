"""Residual analysis: statistical tests that point at what a PSF model lacks.

Each test turns the residuals of a model into one statistic ``z`` in units of its
standard deviation under the null hypothesis "the model and the noise model explain the
image", and compares it with a threshold calibrated on effect-free simulated images
(``bench/bench_diagnose.py``). A test with ``z > threshold`` is *evidence*; the effects
(:mod:`napari_psfspace.core.diagnosis.effects`) read it.

Tests (name: what it looks at)

* ``trend_<variable>``: rank correlation (Spearman, Fisher z) between each bead's
  excess relative error (residual energy minus its noise floor, relative to the bead's
  signal) and ``amplitude``, ``background``, ``subpixel``
  (distance of the centre to the pixel centre), ``neighbour`` (distance to the nearest
  detection), ``radius`` (distance to the field centre), ``row``, ``column``.
* ``core_vs_amplitude``: rank correlation between amplitude and the mean residual of
  the PSF core relative to the amplitude, each bead against its nearest neighbours
  (:func:`core_trend`; flattened bright cores: saturation, nonlinear response; a PSF
  model merely too sharp leaves the same relative residual on all, and its error over
  the field cancels between neighbours).
* ``bead_width``: rank correlation (one-sided, positive) between each bead's flux
  (:func:`bead_flux`) and its width beyond the model (residual on the Laplacian of the
  fitted PSF, :func:`bead_width`): beads of different sizes, the bigger ones brighter.
* ``mean_residual``: chi-square of the mean normalised residual patch (a bias common to
  all beads: the PSF model is wrong everywhere the same way).
* ``coherent_residual``: largest singular value of the matrix of normalised residual
  patches against the Marchenko-Pastur edge of pure noise (structure that varies from
  bead to bead: basis or field model too small).
* ``pixel_outliers``: spots narrower than the optics can form (hot pixels, cosmic
  rays, :mod:`~napari_psfspace.core.beads.spikes`), counted over the whole image.
* ``row_pattern`` / ``column_pattern``: excess variance of the row / column means of
  the bead-free background (pixels within 3 sd of the line's median), line to line
  (fixed-pattern offsets).
* ``background_structure``: chi-square of order-2 polynomials fitted to the bead-free
  pixels of windows of a patch's size (at least a quarter of them bead-free), after
  removing a smooth background, as chi2/dof per window, and their 10 %-trimmed mean
  (structure at the scale of a patch that the per-patch polynomial cannot describe).
  The background tests measure their excess against the noise's sampling error and
  the noise model's own relative error (:func:`noise_scale_error`).
* ``amplitude_field``: F-test of a radial quadratic trend (free centre) of log
  amplitude over the field (vignetting, non-uniform illumination), in the fitted
  amplitudes and in the model-free patch fluxes: the smaller z of the two.
* ``saturation``: pixels at the image's maximum value inside bead cores.
* ``secondary_peaks``: beads whose smoothed normalised residual has a peak of more than
  6 noise sd outside the core (a companion bead the detector merged with it).
* ``elongated_beads``: beads stretched along one axis far more than their neighbours
  (:func:`_elongated_beads`: a companion 1-3 px away, inside the core, merged with it).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi
from scipy import stats

from ..beads.background import monomials
from ..beads.patches import extract_patches
from ..beads.spikes import find_spikes, pixel_noise_sd
from ..beads.window import radial_distance
from .noise import NoiseModel
from .photometry import radial_design, radial_to_monomials
from .residuals import BeadResiduals

#: Default thresholds (z units), calibrated on effect-free simulations.
THRESHOLDS: dict[str, float] = {
    "trend": 4.0,
    "core_vs_amplitude": 4.0,
    "mean_residual": 5.0,
    "coherent_residual": 5.0,
    "pixel_outliers": 3.0,
    "row_pattern": 6.0,
    "column_pattern": 6.0,
    "background_structure": 4.0,
    "amplitude_field": 3.0,
    "saturation": 3.0,
    "secondary_peaks": 3.0,
    "elongated_beads": 3.0,
    "bead_width": 2.5,
}

#: A bead counts as stretched (a merged companion) beyond this many sd of its
#: elongation against its neighbours' (:func:`_elongated_beads`).
ELONGATION_Z = 6.0
#: ... and stretched by more than this fraction of the PSF's variance along one axis
#: (still beads of the scene family reach 0.28 from the model's own error).
MIN_STRETCH = 0.3

TREND_VARIABLES = ("amplitude", "background", "subpixel", "neighbour", "radius", "row",
                   "column")


@dataclass(frozen=True)
class TestResult:
    """One residual test.

    Attributes
    ----------
    name : str
    z : float
        Statistic in null standard deviations (signed for correlations).
    threshold : float
    detail : dict
        Test-specific numbers (JSON-ready).
    """

    name: str
    z: float
    threshold: float
    detail: dict = field(default_factory=dict)
    two_sided: bool = False

    @property
    def strength(self) -> float:
        """``|z|`` for two-sided tests, ``max(z, 0)`` for one-sided ones."""
        if not np.isfinite(self.z):
            return 0.0
        return abs(self.z) if self.two_sided else max(self.z, 0.0)

    @property
    def significant(self) -> bool:
        return self.strength > self.threshold

    @property
    def evidence(self) -> float:
        """``strength / threshold``: above 1 is significant; used to rank effects."""
        return float(self.strength / self.threshold)

    def to_dict(self) -> dict:
        return {"name": self.name, "z": float(self.z), "threshold": self.threshold,
                "two_sided": self.two_sided, "significant": self.significant, **self.detail}


@dataclass
class Analysis:
    """All test results, by name, and the residuals they were computed from."""

    tests: dict[str, TestResult]
    residuals: BeadResiduals | None = field(default=None, repr=False)

    def __getitem__(self, name: str) -> TestResult:
        return self.tests[name]

    def significant(self) -> list[TestResult]:
        """Significant tests, strongest first."""
        return sorted((t for t in self.tests.values() if t.significant),
                      key=lambda t: -t.evidence)

    def to_dict(self) -> dict:
        return {k: t.to_dict() for k, t in self.tests.items()}


def _spearman_z(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Spearman rho and its Fisher z (approximately N(0, 1) under independence)."""
    ok = np.isfinite(x) & np.isfinite(y)
    n = int(ok.sum())
    if n < 8 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return 0.0, 0.0
    rho = float(stats.spearmanr(x[ok], y[ok]).statistic)
    rho = float(np.clip(rho, -0.999999, 0.999999))
    return rho, float(np.arctanh(rho) * np.sqrt((n - 3) / 1.06))


def _chi2_to_z(chi2: float, dof: float) -> float:
    """Wilson-Hilferty normal approximation of a chi-square statistic."""
    if dof <= 0:
        return 0.0
    a = 2.0 / (9.0 * dof)
    return float(((chi2 / dof) ** (1.0 / 3.0) - (1 - a)) / np.sqrt(a))


#: Relative uncertainty of the variance scale of an *assumed* noise model (a fallback:
#: constant variance, unit-gain Poisson), for the tests that compare a chi-square with
#: its noise-only value. The unit-gain fallback overestimated an 8-bit low-gain scene's
#: variance 3-20 times on the scene family.
FALLBACK_SCALE_ERROR = 0.5


def noise_scale_error(noise: NoiseModel) -> float:
    """Relative uncertainty of ``noise``'s variance scale: photon transfer's own
    ``gain_relative_error``, 0 for camera values given, :data:`FALLBACK_SCALE_ERROR`
    for an assumed model.

    The background tests compare a chi-square over hundreds of windows or lines with
    its noise-only value: against the sampling error alone, a gain known to 5 % gave z
    of 10-800 on still scenes of the family. (Measuring the scale on the image's own
    bead-free pixels instead, from second differences, was tried: quantised 8-bit
    backgrounds and faint undetected beads made it worse, 18 of 102 scenes firing.)
    """
    if noise.kind == "camera":
        return 0.0
    if noise.kind == "photon transfer":
        return float((noise.checks or {}).get("gain_relative_error", 0.0) or 0.0)
    return FALLBACK_SCALE_ERROR


#: A line's level is the mean of its bead-free pixels within this many noise sd of its
#: median.
LINE_CLIP = 3.0


def _trim_factor(trim: float) -> float:
    """Asymptotic variance of the ``trim``-trimmed mean of n N(0, 1) values, times n:
    ``(1 - 2a - 2c phi(c) + 2a c^2) / (1 - 2a)^2``, ``c`` the ``(1 - a)`` quantile."""
    if trim <= 0:
        return 1.0
    c = float(stats.norm.isf(trim))
    return (1 - 2 * trim - 2 * c * stats.norm.pdf(c) + 2 * trim * c * c) / (1 - 2 * trim) ** 2


def _excess_z(ratio: float, se_sampling: float, scale_error: float) -> float:
    """A mean chi2/dof ``ratio`` against 1, in units of its sampling error combined with
    the noise model's own relative error (:func:`noise_scale_error`)."""
    return float((ratio - 1.0) / max(np.hypot(se_sampling, scale_error), 1e-12))


def bead_covariates(res: BeadResiduals, shape, all_positions=None) -> dict[str, np.ndarray]:
    """Per-bead variables the trend tests correlate with, each of shape (K,)."""
    pos = res.positions
    h, w = shape
    frac = pos - np.round(pos)
    ref = pos if all_positions is None else np.asarray(all_positions, float).reshape(-1, 2)
    if len(ref) > 1:
        from scipy.spatial import cKDTree

        d, _ = cKDTree(ref).query(pos, k=2)
        nn = np.where(d[:, 0] < 1e-6, d[:, 1], d[:, 0])
    else:
        nn = np.full(len(pos), np.inf)
    return {
        "amplitude": res.amplitude,
        "background": res.background,
        "subpixel": np.hypot(frac[:, 0], frac[:, 1]),
        "neighbour": nn,
        "radius": np.hypot(pos[:, 0] - (h - 1) / 2, pos[:, 1] - (w - 1) / 2),
        "row": pos[:, 0],
        "column": pos[:, 1],
    }


#: Neighbours a bead's value is compared with in :func:`local_contrast`.
LOCAL_K = 6


def local_contrast(values: np.ndarray, positions: np.ndarray, k: int = LOCAL_K) -> np.ndarray:
    """Each bead's value minus the median of its ``k`` nearest beads' (finite) values.

    What varies smoothly over the field (the field model's own error, a vignetting of
    the amplitudes) cancels; what is the bead's own (its brightness) stays. Shape (K,);
    NaN where the value is not finite or no neighbour has one.
    """
    values = np.asarray(values, dtype=np.float64)
    out = np.full(len(values), np.nan)
    ok = np.isfinite(values)
    if ok.sum() < 2:
        return out
    from scipy.spatial import cKDTree

    pos = np.asarray(positions, dtype=np.float64)[ok]
    kk = int(min(k + 1, ok.sum()))
    _, idx = cKDTree(pos).query(pos, k=kk)
    neighbours = values[ok][np.asarray(idx).reshape(len(pos), kk)[:, 1:]]
    out[ok] = values[ok] - np.median(neighbours, axis=1)
    return out


def core_residuals(res: BeadResiduals, core: np.ndarray, data: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Each bead's amplitude and mean core residual relative to it, shapes (K,), (K,).

    Amplitude and background are refitted to the model's shape by *unweighted* least
    squares over the fit mask: with noise weights a bright bead's fit leans on its wings
    and a faint one's on its core, so a shape error alone leaves a core residual that
    changes with brightness. A PSF model merely too sharp (or too flat) leaves the same
    relative core residual on every bead; a nonlinear response or saturation one that
    changes with brightness.

    Parameters
    ----------
    res : BeadResiduals
    core : ndarray of shape (P, P), bool
        The PSF core.
    data : ndarray of shape (K, P, P), optional
        Pixels to fit instead of ``res.data`` (e.g. linearised).
    """
    data = res.data if data is None else data
    scale = np.where(res.amplitude == 0, 1.0, res.amplitude)[:, None, None]
    shape_ = (res.model - res.background[:, None, None]) / scale
    m = res.fit_mask.astype(np.float64)
    ax = (1, 2)
    n, s1, s2 = m.sum(ax), (m * shape_).sum(ax), (m * shape_ ** 2).sum(ax)
    d1, sd = (m * data).sum(ax), (m * shape_ * data).sum(ax)
    det = s2 * n - s1 ** 2
    good = det > 1e-12 * np.maximum(s2 * n, 1e-300)
    det = np.where(good, det, 1.0)
    amp = np.where(good, (sd * n - s1 * d1) / det, np.nan)
    bg = np.where(good, (s2 * d1 - s1 * sd) / det, np.nan)
    inner = core[None] & res.fit_mask
    n_core = inner.sum(ax)
    r = data - amp[:, None, None] * shape_ - bg[:, None, None]
    core_sum = np.where(inner, r, 0.0).sum(ax)
    ok = good & (n_core > 0) & (amp > 0)
    core_rel = np.full(len(amp), np.nan)
    core_rel[ok] = core_sum[ok] / n_core[ok] / amp[ok]
    return amp, core_rel


def core_trend(amplitude: np.ndarray, core_rel: np.ndarray, positions: np.ndarray
               ) -> tuple[float, float]:
    """Spearman rho and z of the core residual against brightness, bead against its
    neighbours (:func:`local_contrast` of both): a nonlinear response or saturation
    makes a bead's core flatter than its neighbours' the brighter it is than them."""
    amp = np.where(amplitude > 0, amplitude, np.nan)
    return _spearman_z(local_contrast(np.log(amp), positions),
                       local_contrast(core_rel, positions))


def outlier_pixels(img: np.ndarray, noise: NoiseModel, k: float = 8.0) -> np.ndarray:
    """Pixels narrower than the optics can form (hot pixels, cosmic rays) standing ``k``
    noise sd out (:func:`~napari_psfspace.core.beads.spikes.find_spikes`), shape (S, 2); the
    noise sd is the model's at the image's median level, or the image's own where that
    is larger."""
    sd = float(np.sqrt(noise.variance(float(np.median(img[::4, ::4])))))
    return find_spikes(img, noise_sd=max(sd, pixel_noise_sd(img)), k=k)


def _pixel_outliers(img: np.ndarray, noise: NoiseModel, k: float = 8.0) -> dict:
    found = outlier_pixels(img, noise, k)
    return {"count": int(len(found)), "positions": found[:200].tolist()}


def _secondary_peaks(res: BeadResiduals, psf_radius: float, k: float = 6.0,
                     relative: float = 0.15) -> dict:
    """Beads with a companion: a peak of the smoothed residual outside the core that
    stands ``k`` noise sd out *and* exceeds ``relative`` of the bead's own peak (a model
    that is merely imperfect leaves a few per cent of the peak, a merged companion bead
    30-100 %)."""
    p = res.data.shape[-1]
    dist = radial_distance(p)
    # the ring between the core and the fit radius (smoothing bleeds zeros from beyond)
    ring = (dist > max(2.0, psf_radius / 3)) & (dist < psf_radius - 1.5)
    resid = ndi.gaussian_filter(res.residual, (0, 1.0, 1.0))
    noise = ndi.gaussian_filter(np.where(res.fit_mask, res.normalised_residual, 0.0),
                                (0, 1.0, 1.0))
    sd = 1.4826 * float(np.median(np.abs(noise[:, ring] - np.median(noise[:, ring])))) or 1.0
    signal = (res.model - res.background[:, None, None]).reshape(len(res), -1).max(axis=1)
    peak_adu = resid[:, ring].max(axis=1)
    peak_sd = (noise[:, ring].max(axis=1)) / sd
    hits = np.flatnonzero((peak_sd > k) & (peak_adu > relative * np.maximum(signal, 1e-12)))
    ring_idx = np.flatnonzero(ring.ravel())
    at = ring_idx[np.argmax(resid[:, ring][hits], axis=1)] if len(hits) else np.zeros(0, int)
    base = np.round(res.positions[hits])
    peaks = base + np.column_stack([at // p - p // 2, at % p - p // 2])
    return {"count": int(len(hits)), "beads": hits.tolist(), "peaks": peaks.tolist(),
            "max_relative": float((peak_adu / np.maximum(signal, 1e-12)).max())
            if len(res) else 0.0}


def bead_width(res: BeadResiduals) -> np.ndarray:
    """Each bead's width beyond its model, shape (K,), pixels squared.

    The weighted least-squares coefficient ``s`` of the bead's residual on the
    Laplacian of its fitted PSF ``L = lap(A m)`` (made orthogonal to the fitted
    amplitude and background): a bead blurred by an extra isotropic Gaussian of
    variance ``tau`` per axis is ``A m + (tau / 2) L``, so ``s ~ tau / 2``; positive:
    wider than the model, negative: sharper.
    """
    sig = res.model - res.background[:, None, None]
    kern = np.array([[[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]]])
    lap = ndi.convolve(sig, kern, mode="constant")
    w = res.fit_mask / res.variance
    out = np.zeros(len(res))
    for i in range(len(res)):
        use = res.fit_mask[i]
        if not use.any():
            continue
        wi = w[i][use]
        design = np.column_stack([sig[i][use], np.ones(use.sum())]) * np.sqrt(wi)[:, None]
        lw = lap[i][use] * np.sqrt(wi)
        coef, *_ = np.linalg.lstsq(design, lw, rcond=None)
        perp = lw - design @ coef  # Laplacian beyond amplitude and background
        rw = (res.data[i] - res.model[i])[use] * np.sqrt(wi)
        out[i] = float(rw @ perp) / max(float(perp @ perp), 1e-300)
    return out


def bead_elongation(res: BeadResiduals) -> tuple[np.ndarray, np.ndarray]:
    """Each bead's elongation beyond its model and its noise standard error, shapes
    (K, 2), (K, 2), pixels squared.

    The weighted least-squares coefficients of the bead's residual on the anisotropic
    second derivatives of its fitted PSF ``S = A m``, ``S_xx - S_yy`` and ``2 S_xy``
    (jointly with ``S``, a constant and the Laplacian, which take up amplitude,
    background and width): a bead stretched by an extra Gaussian of covariance
    ``[[a, c], [c, b]]`` is ``S + (a - b)/4 (S_xx - S_yy) + c/2 (2 S_xy) + ...``.
    A companion bead 1-3 px away, which the detector merged with the bead, stretches it
    along their axis; a bigger bead widens it the same way in every direction.
    """
    sig = res.model - res.background[:, None, None]
    sxx = np.gradient(np.gradient(sig, axis=2), axis=2)
    syy = np.gradient(np.gradient(sig, axis=1), axis=1)
    sxy = np.gradient(np.gradient(sig, axis=1), axis=2)
    w = res.fit_mask / res.variance
    coef_out = np.zeros((len(res), 2))
    se_out = np.full((len(res), 2), np.inf)
    for i in range(len(res)):
        use = res.fit_mask[i]
        if use.sum() < 8:
            continue
        sw = np.sqrt(w[i][use])
        design = np.column_stack([sig[i][use], np.ones(use.sum()), sxx[i][use] + syy[i][use],
                                  sxx[i][use] - syy[i][use], 2 * sxy[i][use]]) * sw[:, None]
        rw = (res.data[i] - res.model[i])[use] * sw
        gram = design.T @ design
        try:
            cov = np.linalg.inv(gram)
        except np.linalg.LinAlgError:
            continue
        coef = cov @ (design.T @ rw)
        coef_out[i] = coef[3:]
        se_out[i] = np.sqrt(np.maximum(np.diag(cov)[3:], 0.0))
    return coef_out, se_out


def _psf_variance(res: BeadResiduals) -> np.ndarray:
    """Each bead's model PSF variance per axis (second moment of its positive part about
    the patch centre, over 2), shape (K,), pixels squared."""
    sig = np.clip(res.model - res.background[:, None, None], 0.0, None)
    p = sig.shape[-1]
    r2 = radial_distance(p) ** 2
    total = sig.sum(axis=(1, 2))
    return (sig * r2).sum(axis=(1, 2)) / np.maximum(total, 1e-300) / 2.0


def _elongated_beads(res: BeadResiduals, k: float = ELONGATION_Z) -> dict:
    """Beads stretched far more than their neighbours (a merged companion 1-3 px away).

    Each bead's elongation (:func:`bead_elongation`) minus its nearest neighbours'
    (:func:`local_contrast`: the field's own astigmatism, and the model's error over
    the field, cancel), in units of its noise and of the scatter from bead to bead
    beyond it (``tau``, set so that the median bead scores the median of a chi-square
    of 2 dof); beads beyond ``k`` and stretched by more than :data:`MIN_STRETCH` of the
    PSF's variance are counted.
    """
    e, se = bead_elongation(res)
    ok = np.all(np.isfinite(se), axis=1) & (res.amplitude > 0)
    out = {"count": 0, "beads": [], "tau": 0.0, "max_z": 0.0}
    if ok.sum() < 12:
        return out
    idx = np.flatnonzero(ok)
    c = np.column_stack([local_contrast(e[ok, j], res.positions[ok]) for j in (0, 1)])
    s2 = se[ok] ** 2
    good = np.all(np.isfinite(c), axis=1)
    c, s2, idx = c[good], s2[good], idx[good]

    def score(tau2):
        return np.sum(c ** 2 / (s2 + tau2), axis=1)

    target = float(stats.chi2.median(2))
    lo, hi = 0.0, float(np.max(c ** 2)) + 1e-300
    if np.median(score(0.0)) > target:
        for _ in range(60):  # bisection: the median score falls as tau grows
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.median(score(mid)) > target else (lo, mid)
        tau2 = hi
    else:
        tau2 = 0.0
    z = np.sqrt(score(tau2))
    # and a stretch no model error makes: the model's error is heavy-tailed from bead to
    # bead in bright or sparse fields (on the scene family still beads reached z = 31,
    # stretched by up to 28 % of the PSF's variance; a companion 1-3 px away at 50-100 %
    # brightness stretches by 3-180 %)
    var = _psf_variance(res)[idx]
    stretch = 4.0 * np.hypot(e[idx, 0], e[idx, 1]) / np.maximum(var, 1e-12)
    hits = idx[(z > k) & (stretch > MIN_STRETCH)]
    out.update(count=int(len(hits)), beads=hits.tolist(), tau=float(np.sqrt(tau2)),
               max_z=float(z.max()) if len(z) else 0.0)
    return out


def bead_flux(image: np.ndarray, positions, psf_radius: float) -> np.ndarray:
    """Model-free integrated intensity of each bead, shape (K,), image units: the sum of
    its background-free, windowed patch
    (:func:`~napari_psfspace.core.beads.patches.extract_patches`)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    if len(pos) == 0:
        return np.zeros(0)
    return extract_patches(image, pos, psf_radius).flux


def bead_free_mask(shape, positions, psf_radius: float) -> np.ndarray:
    """True farther than ``1.5 psf_radius`` from every position, shape ``shape``."""
    mask = np.zeros(shape, bool)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    iy = np.clip(np.round(pos[:, 0]).astype(int), 0, shape[0] - 1)
    ix = np.clip(np.round(pos[:, 1]).astype(int), 0, shape[1] - 1)
    mask[iy, ix] = True
    return ~ndi.binary_dilation(mask, iterations=int(np.ceil(1.5 * psf_radius)))


def _smooth_background(img: np.ndarray, free: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised (masked) Gaussian smoothing of the bead-free pixels."""
    num = ndi.gaussian_filter(np.where(free, img, 0.0), sigma, mode="nearest")
    den = ndi.gaussian_filter(free.astype(np.float64), sigma, mode="nearest")
    return num / np.maximum(den, 1e-6)


def _line_pattern(resid: np.ndarray, level: np.ndarray, free: np.ndarray, noise: NoiseModel,
                  axis: int, scale_error: float = 0.0) -> dict:
    """Excess variance of the clipped means of bead-free, detrended pixels along rows
    (axis=1) or columns (axis=0), line to line, as a z against the noise (with the
    noise model's relative error ``scale_error``, see :func:`noise_scale_error`)."""
    data = np.where(free, resid, np.nan)
    lvl = np.where(free, level, np.nan)
    if axis == 0:  # one line per row of the transposed arrays
        data, lvl = data.T, lvl.T
    with warnings.catch_warnings():  # lines without a bead-free pixel: NaN, left out
        warnings.simplefilter("ignore", RuntimeWarning)
        lev = np.nanmedian(lvl, axis=1)
        centre = np.nanmedian(data, axis=1)
    # a line's level is the mean of its pixels within LINE_CLIP sd of its median:
    # robust to a faint bead's wing or a hot pixel, and, unlike the median (or a trimmed
    # mean), not stuck to whole ADU on an integer image whose noise is below one ADU (an
    # 8-bit low-gain scene's medians flip between two integers from line to line: z
    # 20-75 on still scenes of the family). On integer images the window spans at least
    # +-1.5 ADU, so that the neighbours of the median's integer stay in
    sd = np.sqrt(noise.variance(np.nan_to_num(lev)))
    half = np.maximum(LINE_CLIP * sd, 1.5 if noise.min_variance > 0 else 0.0)
    with np.errstate(invalid="ignore"):
        inside = np.abs(data - centre[:, None]) <= half[:, None]
    count = inside.sum(axis=1)
    med = np.where(inside, data, 0.0).sum(axis=1) / np.maximum(count, 1)
    ok = (count >= 20) & np.isfinite(centre)
    if ok.sum() < 10:
        return {"z": 0.0, "n_lines": int(ok.sum())}
    m = med[ok]
    # a fixed pattern is line-to-line jitter: compare each line with the mean of its
    # +-4 neighbours (slow trends of the background left by the smoothing cancel out)
    kern = np.ones(9) / 8.0
    kern[4] = 0.0
    local = ndi.convolve1d(m, kern, mode="reflect")
    dev = m - local
    # variance of the mean of normal values clipped at +-c sd
    c = half[ok] / sd[ok]
    clipped = 1.0 - 2.0 * c * stats.norm.pdf(c) / np.maximum(2.0 * stats.norm.cdf(c) - 1.0,
                                                             1e-12)
    var_line = clipped * noise.variance(lev[ok]) / count[ok]
    n = int(ok.sum())
    ratio = float(np.mean(dev**2 / (var_line * (1 + 1 / 8))))
    return {"z": _excess_z(ratio, np.sqrt(2.0 / n), scale_error), "n_lines": n,
            "chi2_dof": ratio, "rms_adu": float(np.sqrt(np.mean(dev**2)))}


def _window_structure(resid: np.ndarray, level: np.ndarray, free: np.ndarray,
                      noise: NoiseModel, size: int, *, min_free: float = 0.25,
                      trim: float = 0.1, scale_error: float = 0.0) -> dict:
    """Order-2 polynomials fitted to the bead-free pixels of windows of a patch's size.

    The image is tiled with ``size x size`` windows; those whose bead-free fraction is
    at least ``min_free`` (with a large PSF, or structure detected as beads, hardly any
    window is wholly bead-free) get an order-2 polynomial fitted by least squares to
    their bead-free pixels, and the chi-square of the fit under the noise model becomes
    a normal z (Wilson-Hilferty). Structure sits
    in some windows only: the statistic is the ``trim``-trimmed mean of the windows' z
    (robust to a few windows spoilt by a bead's wing or a hot pixel), scaled to unit
    variance under the null (1.0605 / n for a 10 % trim of normal values).

    Parameters
    ----------
    resid : ndarray of shape (M, N)
        Image minus its smooth background, ADU.
    level : ndarray of shape (M, N)
        Smooth background, ADU (the noise model's expected value).
    free : ndarray of shape (M, N), bool
        Bead-free pixels.
    noise : NoiseModel
    size : int
        Window size, pixels (the patch size).

    Returns
    -------
    dict
        ``z``, ``windows`` (number used), ``median_chi2_dof``.
    """
    design = monomials(size, 2)
    n_par = design.shape[1]
    h, w = resid.shape
    ratios, dofs = [], []
    for y0 in range(0, h - size + 1, size):
        for x0 in range(0, w - size + 1, size):
            use = free[y0:y0 + size, x0:x0 + size].ravel()
            n_use = int(use.sum())
            if n_use < max(min_free * size * size, 4 * n_par):
                continue
            d = resid[y0:y0 + size, x0:x0 + size].ravel()[use]
            a = design[use]
            coef, *_ = np.linalg.lstsq(a, d, rcond=None)
            var = noise.variance(level[y0:y0 + size, x0:x0 + size].ravel()[use])
            chi2 = float(np.sum((d - a @ coef) ** 2 / var))
            ratios.append(chi2 / (n_use - n_par))
            dofs.append(n_use - n_par)
    if len(ratios) < 5:
        return {"z": 0.0, "windows": len(ratios)}
    n = len(ratios)
    cut = int(trim * n)
    kept = np.sort(ratios)[cut:n - cut]
    # the trimmed mean of the windows' chi2/dof against 1: its sampling error (each
    # window's sqrt(2 / dof), trimmed) combined with the noise model's own relative error
    se = float(np.sqrt(_trim_factor(trim) * 2.0 / np.mean(dofs) / n))
    mean = float(np.mean(kept))
    return {"z": _excess_z(mean, se, scale_error), "windows": n,
            "chi2_dof": mean, "median_chi2_dof": float(np.median(ratios))}


def _radial_trend(positions, values, shape, threshold: float) -> dict:
    """F-test of a paraboloid of revolution (free centre) in ``log(values)`` over the
    field: ``z`` (normal equivalent of the F-test's p), ``F``, ``p``, the radial
    coefficients as monomials, and the smallest centred fall-off to the corners
    (``u^2 + v^2 = 2``) these beads would show at ``threshold``."""
    x = radial_design(positions, shape)
    y = np.log(np.asarray(values, dtype=np.float64))
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
    rss1 = float(np.sum((y - x @ beta) ** 2))
    rss0 = float(np.sum((y - y.mean()) ** 2))
    n, q = len(y), x.shape[1] - 1
    f = ((rss0 - rss1) / q) / max(rss1 / (n - q - 1), 1e-300)
    pval = float(stats.f.sf(f, q, n - q - 1))
    # the beads' own brightness spread and their number set the smallest visible
    # fall-off (a 40 % vignetting is not always seen on 150 beads of spread 0.25)
    cov = np.linalg.pinv(x.T @ x) * rss1 / max(n - q - 1, 1)
    g_min = threshold * float(np.sqrt(max(cov[3, 3], 0.0)))
    return {"z": float(stats.norm.isf(max(pval, 1e-300))), "F": float(f), "p": pval,
            "min_corner_loss": float(1.0 - np.exp(-2.0 * g_min)),
            "coefficients": radial_to_monomials(beta).round(4).tolist()}


def analyse(
    res: BeadResiduals,
    image: np.ndarray,
    noise: NoiseModel,
    *,
    psf_radius: float,
    all_positions=None,
    bead_mask: np.ndarray | None = None,
    thresholds: dict[str, float] | None = None,
) -> Analysis:
    """Run every residual test.

    Parameters
    ----------
    res : BeadResiduals
        Per-bead fits of the model (from
        :func:`~napari_psfspace.core.diagnosis.residuals.fit_beads`).
    image : ndarray of shape (M, N)
        The raw image in ADU.
    noise : NoiseModel
    psf_radius : float
        PSF radius in pixels.
    all_positions : array_like of shape (L, 2), optional
        Every detection (for the nearest-neighbour distances).
    bead_mask : ndarray of shape (M, N), bool, optional
        True near beads (excluded from the background tests). Default: disks of
        ``1.5 psf_radius`` around ``all_positions`` (or the fitted beads).
    thresholds : dict, optional
        Overrides of :data:`THRESHOLDS`.

    Returns
    -------
    Analysis
    """
    th = {**THRESHOLDS, **(thresholds or {})}
    img = np.asarray(image, dtype=np.float64)
    tests: dict[str, TestResult] = {}
    k = len(res)
    # the model's own relative error per bead, noise removed: independent of the bead's
    # brightness when the model is merely imperfect, growing with it (say) when the
    # detector saturates
    excess = res.rel_energy - res.floor
    cov = bead_covariates(res, img.shape, all_positions)
    for name in TREND_VARIABLES:
        rho, z = _spearman_z(cov[name], excess)
        tests[f"trend_{name}"] = TestResult(f"trend_{name}", z, th["trend"], {"rho": rho},
                                            two_sided=True)

    nres = np.where(res.fit_mask, res.normalised_residual, np.nan)
    p = nres.shape[-1]
    core = radial_distance(p) <= max(1.5, psf_radius / 4)
    amp, core_rel = core_residuals(res, core)
    rho, z = core_trend(amp, core_rel, res.positions)
    tests["core_vs_amplitude"] = TestResult("core_vs_amplitude", z, th["core_vs_amplitude"],
                                            {"rho": rho}, two_sided=True)
    # beads of different sizes: the bigger beads are brighter *and* wider than the model;
    # brightness from the model-free patch flux (a poor model's amplitudes are not)
    width = bead_width(res)
    flux = bead_flux(img, res.positions, psf_radius)
    ok = (flux > 0) & (res.amplitude > 0)
    rho, z = _spearman_z(flux[ok], width[ok])
    tests["bead_width"] = TestResult("bead_width", z, th["bead_width"],
                                     {"rho": rho, "n_beads": int(ok.sum())})

    common = np.all(res.fit_mask, axis=0)
    flat = np.nan_to_num(nres[:, common])  # (K, n_pix)
    if k >= 5:
        mean = flat.mean(axis=0)
        chi2 = float(np.sum(mean**2 * k))
        tests["mean_residual"] = TestResult("mean_residual", _chi2_to_z(chi2, flat.shape[1]),
                                            th["mean_residual"], {"chi2": chi2,
                                                                  "n_pixels": int(flat.shape[1])})
        s = np.linalg.svd(flat - mean, compute_uv=False)
        edge = np.sqrt(k - 1) + np.sqrt(flat.shape[1])
        # fluctuation of the top singular value at the MP edge ~ edge^(1/3) (Tracy-Widom)
        scale = edge ** (1 / 3) * (1 / np.sqrt(k - 1) + 1 / np.sqrt(flat.shape[1])) ** (1 / 3)
        z = (s[0] - edge) / max(scale, 1e-9)
        tests["coherent_residual"] = TestResult("coherent_residual", float(z),
                                                th["coherent_residual"],
                                                {"s1_over_edge": float(s[0] / edge)})

    out = _pixel_outliers(img, noise)
    tests["pixel_outliers"] = TestResult("pixel_outliers", float(out["count"]),
                                         th["pixel_outliers"], out)

    if bead_mask is None:
        ref = res.positions if all_positions is None else np.asarray(all_positions)
        free = bead_free_mask(img.shape, ref, psf_radius)
    else:
        free = ~np.asarray(bead_mask, bool)
    level = _smooth_background(img, free, sigma=max(8.0, 2 * psf_radius))
    resid = img - level
    # each against the noise's sampling error and the noise model's own uncertainty
    scale_error = noise_scale_error(noise)
    for axis, name in ((1, "row_pattern"), (0, "column_pattern")):
        d = _line_pattern(resid, level, free, noise, axis, scale_error)
        tests[name] = TestResult(name, d.pop("z"), th[name], d)
    d = _window_structure(resid, level, free, noise, p, scale_error=scale_error)
    tests["background_structure"] = TestResult("background_structure", d.pop("z"),
                                               th["background_structure"], d)

    if k >= 5:
        ok = (res.amplitude > 0) & (flux > 0)
        if ok.sum() >= 12:
            # vignetting / an off-centre illumination spot: a paraboloid of revolution
            # with a free centre, as the throughput is fitted (3 dof, not the full
            # quadratic's 5: on 150 beads of brightness spread 0.25 a 40 % fall-off to
            # the corners gave F = 4.4, z = 3.1). A throughput shows in the model-free
            # patch fluxes as much as in the fitted amplitudes; a PSF model whose error
            # grows towards the edge biases the amplitudes alone (still scenes of the
            # family: z 2.8 and 3.2 from the amplitudes, 2.1 and 1.6 from the fluxes,
            # 1.6 from the true amplitudes). The test's z is the smaller of the two
            d_amp = _radial_trend(res.positions[ok], res.amplitude[ok], img.shape,
                                  th["amplitude_field"])
            d_flux = _radial_trend(res.positions[ok], flux[ok], img.shape,
                                   th["amplitude_field"])
            z = min(d_amp["z"], d_flux["z"])
            tests["amplitude_field"] = TestResult(
                "amplitude_field", z, th["amplitude_field"],
                {"F": d_amp["F"], "p": d_amp["p"], "z_amplitude": d_amp["z"],
                 "z_flux": d_flux["z"], "F_flux": d_flux["F"],
                 "min_corner_loss": d_amp["min_corner_loss"],
                 "coefficients": d_amp["coefficients"]})
    # row / column patterns and background structure use the bead-free background
    d = _secondary_peaks(res, psf_radius)
    tests["secondary_peaks"] = TestResult("secondary_peaks", float(d["count"]),
                                          th["secondary_peaks"], d)
    d = _elongated_beads(res)
    tests["elongated_beads"] = TestResult("elongated_beads", float(d["count"]),
                                          th["elongated_beads"], d)
    top = float(img.max())
    cores = np.zeros(img.shape, bool)
    iy = np.clip(np.round(res.positions[:, 0]).astype(int), 0, img.shape[0] - 1)
    ix = np.clip(np.round(res.positions[:, 1]).astype(int), 0, img.shape[1] - 1)
    cores[iy, ix] = True
    cores = ndi.binary_dilation(cores, iterations=max(1, int(psf_radius / 3)))
    n_top = int(np.count_nonzero((img >= top) & cores))
    tests["saturation"] = TestResult("saturation", float(n_top if n_top >= 2 else 0),
                                     th["saturation"], {"level": top, "pixels": n_top})
    return Analysis(tests, res)
