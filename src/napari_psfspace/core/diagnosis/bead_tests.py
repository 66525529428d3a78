"""Residual tests read bead by bead: covariates of each bead (brightness, background,
position, sub-pixel phase, neighbours), the core's residual against brightness, a
bead's width and elongation against its neighbours', secondary peaks in its patch, and
its flux.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy import stats

from ..beads.patches import extract_patches
from ..beads.window import radial_distance
from .residuals import BeadResiduals
from .statistics import spearman_z

#: A bead counts as stretched (a merged companion) beyond this many sd of its
#: elongation against its neighbours' (:func:`elongated_beads`).
ELONGATION_Z = 6.0
#: ... and stretched by more than this fraction of the PSF core's variance along one
#: axis (:data:`CORE_FRACTION`): the variance over the whole patch grows with the wings
#: that aberrations and diffraction rings carry, and hid the stretch of doublets whose
#: cores it doubles (companions).
MIN_STRETCH = 0.3
#: Beads whose elongation score exceeds this are left out of the response's trend
#: (:func:`round_beads`).
ROUND_Z = 3.0
#: The core whose second moment sets the PSF's variance: within this fraction of the
#: PSF radius of the centre.
CORE_FRACTION = 0.5


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
    return spearman_z(local_contrast(np.log(amp), positions),
                       local_contrast(core_rel, positions))


def secondary_peaks(res: BeadResiduals, psf_radius: float, k: float = 6.0,
                     relative: float = 0.15) -> dict:
    """Beads with a companion: a peak of the smoothed residual outside the core that
    stands ``k`` noise sd out *and* exceeds ``relative`` of the bead's own peak (a model
    that is merely imperfect leaves a few per cent of the peak, a merged companion bead
    30-100 %)."""
    p = res.data.shape[-1]
    dist = radial_distance(p)
    # the ring between the core and the fit radius (smoothing bleeds zeros from beyond)
    ring = (dist > max(2.0, psf_radius / 3)) & (dist < psf_radius - 1.5)
    if len(res) == 0 or not ring.any():  # a PSF too small for a ring beside its core
        return {"count": 0, "beads": [], "peaks": [], "max_relative": 0.0,
                "note": f"not tested: no ring between the core and the fit radius at a PSF "
                        f"radius of {psf_radius:g} px"}
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


def _psf_variance(res: BeadResiduals, within: float | None = None) -> np.ndarray:
    """Each bead's model PSF variance per axis (second moment of its positive part about
    the patch centre, over 2, within ``within`` px of it: None, the whole patch), shape
    (K,), pixels squared."""
    sig = np.clip(res.model - res.background[:, None, None], 0.0, None)
    p = sig.shape[-1]
    r2 = radial_distance(p) ** 2
    if within is not None:
        sig = sig * (r2 <= within ** 2)
    total = sig.sum(axis=(1, 2))
    return (sig * r2).sum(axis=(1, 2)) / np.maximum(total, 1e-300) / 2.0


def elongation_scores(res: BeadResiduals, *, psf_radius: float | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Each bead's elongation against its neighbours' (:func:`elongated_beads`).

    Returns
    -------
    beads : ndarray of shape (J,), int
        The beads scored (finite elongation, positive amplitude; none with fewer than 12).
    z : ndarray of shape (J,)
        Their elongation contrast in units of its noise and of the scatter beyond it.
    stretch : ndarray of shape (J,)
        Their stretch over the variance of the PSF's core.
    tau : float
        The bead-to-bead scatter beyond the noise.
    """
    e, se = bead_elongation(res)
    ok = np.all(np.isfinite(se), axis=1) & (res.amplitude > 0)
    if ok.sum() < 12:
        return np.zeros(0, int), np.zeros(0), np.zeros(0), 0.0
    idx = np.flatnonzero(ok)
    c = np.column_stack([local_contrast(e[ok, j], res.positions[ok]) for j in (0, 1)])
    s2 = se[ok] ** 2
    good = np.all(np.isfinite(c), axis=1)
    c, s2, idx = c[good], s2[good], idx[good]

    def score(tau2):
        return np.sum(c ** 2 / (s2 + tau2), axis=1)

    target = float(stats.chi2.median(2))
    lo, hi = 0.0, float(np.max(c ** 2)) + 1e-300 if len(c) else 1e-300
    if len(c) and np.median(score(0.0)) > target:
        for _ in range(60):  # bisection: the median score falls as tau grows
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.median(score(mid)) > target else (lo, mid)
        tau2 = hi
    else:
        tau2 = 0.0
    z = np.sqrt(score(tau2))
    # and a stretch no model error makes: the model's error is heavy-tailed from bead to
    # bead in bright or sparse fields, where still beads reach large z with a small
    # stretch; a merged companion stretches a bead by much more (bench/bench_diagnose.py)
    var = _psf_variance(res, None if psf_radius is None
                        else max(1.5, CORE_FRACTION * psf_radius))[idx]
    stretch = 4.0 * np.hypot(e[idx, 0], e[idx, 1]) / np.maximum(var, 1e-12)
    return idx, z, stretch, float(np.sqrt(tau2))


def elongated_beads(res: BeadResiduals, k: float = ELONGATION_Z, *,
                    psf_radius: float | None = None, scores=None) -> dict:
    """Beads stretched far more than their neighbours (a merged companion 1-3 px away).

    Each bead's elongation (:func:`bead_elongation`) minus its nearest neighbours'
    (:func:`local_contrast`: the field's own astigmatism, and the model's error over
    the field, cancel), in units of its noise and of the scatter from bead to bead
    beyond it (``tau``, set so that the median bead scores the median of a chi-square
    of 2 dof); beads beyond ``k`` and stretched by more than :data:`MIN_STRETCH` of the
    variance of the PSF's core (within :data:`CORE_FRACTION` of ``psf_radius``, at least
    1.5 px; None: the whole patch) are counted. ``scores``: those of
    :func:`elongation_scores` for the same ``psf_radius``, when already computed.
    """
    idx, z, stretch, tau = (elongation_scores(res, psf_radius=psf_radius) if scores is None
                            else scores)
    out = {"count": 0, "beads": [], "tau": tau, "max_z": 0.0}
    if len(idx) == 0:
        return out
    hits = idx[(z > k) & (stretch > MIN_STRETCH)]
    out.update(count=int(len(hits)), beads=hits.tolist(), max_z=float(z.max()))
    return out


def round_beads(res: BeadResiduals, *, psf_radius: float | None = None,
                k: float = ROUND_Z, scores=None) -> np.ndarray:
    """The beads no more elongated than their neighbours, by ``k`` of the score of
    :func:`elongation_scores`, shape (K,) bool (all, where too few beads are scored).

    A companion merged with its bead makes that bead brighter *and* its core flatter
    than a single bead's, as a compressive response does to the brightest beads; the
    response's trend (:func:`core_trend`) is read on the round beads only. A compressive
    response keeps beads round: beyond ``k`` = 3 a chi-square of 2 dof leaves about 1 %
    of them out. ``scores``: as in :func:`elongated_beads`.
    """
    keep = np.ones(len(res), bool)
    idx, z, _, _ = (elongation_scores(res, psf_radius=psf_radius) if scores is None
                    else scores)
    keep[idx[z > k]] = False
    return keep


def bead_flux(image: np.ndarray, positions, psf_radius: float) -> np.ndarray:
    """Model-free integrated intensity of each bead, shape (K,), image units: the sum of
    its background-free, windowed patch
    (:func:`~napari_psfspace.core.beads.patches.extract_patches`)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    if len(pos) == 0:
        return np.zeros(0)
    return extract_patches(image, pos, psf_radius).flux
