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
  (:func:`elongated_beads`: a companion 1-3 px away, inside the core, merged with it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from ..beads.noise import NoiseModel
from ..beads.window import radial_distance
from .background_tests import (
    bead_free_mask,
    line_pattern,
    pixel_outliers,
    smooth_background,
    window_structure,
)
from .bead_tests import (
    bead_covariates,
    bead_flux,
    bead_width,
    core_residuals,
    core_trend,
    elongated_beads,
    elongation_scores,
    round_beads,
    secondary_peaks,
)
from .residuals import BeadResiduals
from .statistics import chi2_to_z, noise_scale_error, radial_trend, spearman_z

#: Default thresholds (z units), calibrated on effect-free simulations.
THRESHOLDS: dict[str, float] = {
    "trend": 4.0,
    # a Spearman z, set from its spread on effect-free scenes of the three optics codes
    # (the compressive response): a weak response reads a few sd
    "core_vs_amplitude": 3.0,
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
        rho, z = spearman_z(cov[name], excess)
        tests[f"trend_{name}"] = TestResult(f"trend_{name}", z, th["trend"], {"rho": rho},
                                            two_sided=True)

    nres = np.where(res.fit_mask, res.normalised_residual, np.nan)
    p = nres.shape[-1]
    core = radial_distance(p) <= max(1.5, psf_radius / 4)
    amp, core_rel = core_residuals(res, core)
    # on the round beads: a merged companion flattens its bead's core as it brightens it
    scores = elongation_scores(res, psf_radius=psf_radius)  # read here and below
    round_ = round_beads(res, scores=scores)
    rho, z = core_trend(np.where(round_, amp, np.nan), core_rel, res.positions)
    tests["core_vs_amplitude"] = TestResult("core_vs_amplitude", z, th["core_vs_amplitude"],
                                            {"rho": rho, "left_out_elongated":
                                             int(np.count_nonzero(~round_))},
                                            two_sided=True)
    # beads of different sizes: the bigger beads are brighter *and* wider than the model;
    # brightness from the model-free patch flux (a poor model's amplitudes are not)
    width = bead_width(res)
    flux = bead_flux(img, res.positions, psf_radius)
    ok = (flux > 0) & (res.amplitude > 0)
    rho, z = spearman_z(flux[ok], width[ok])
    tests["bead_width"] = TestResult("bead_width", z, th["bead_width"],
                                     {"rho": rho, "n_beads": int(ok.sum())})

    _common_residual_tests(res, th, tests, k, nres)

    out = pixel_outliers(img, noise)
    tests["pixel_outliers"] = TestResult("pixel_outliers", float(out["count"]),
                                         th["pixel_outliers"], out)

    _background_tests(res, noise, psf_radius, all_positions, bead_mask, th, img, tests, p)

    _amplitude_field_test(res, th, img, tests, k, flux)
    d = secondary_peaks(res, psf_radius)
    tests["secondary_peaks"] = TestResult("secondary_peaks", float(d["count"]),
                                          th["secondary_peaks"], d)
    d = elongated_beads(res, psf_radius=psf_radius, scores=scores)
    tests["elongated_beads"] = TestResult("elongated_beads", float(d["count"]),
                                          th["elongated_beads"], d)
    _saturation_test(res, psf_radius, all_positions, th, img, tests)
    return Analysis(tests, res)


def _common_residual_tests(res, th, tests, k, nres):
    """A residual common to the beads: their mean normalised residual (chi-square), and its
    coherent part (the top singular value against the Marchenko-Pastur edge)."""
    common = np.all(res.fit_mask, axis=0)
    flat = np.nan_to_num(nres[:, common])  # (K, n_pix)
    if k >= 5:
        mean = flat.mean(axis=0)
        chi2 = float(np.sum(mean**2 * k))
        tests["mean_residual"] = TestResult("mean_residual", chi2_to_z(chi2, flat.shape[1]),
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


def _background_tests(res, noise, psf_radius, all_positions, bead_mask, th, img, tests, p):
    """Row and column patterns and structure of the bead-free background, each against the
    noise's sampling error and the noise model's own uncertainty."""
    if bead_mask is None:
        ref = res.positions if all_positions is None else np.asarray(all_positions)
        free = bead_free_mask(img.shape, ref, psf_radius)
    else:
        free = ~np.asarray(bead_mask, bool)
    level = smooth_background(img, free, sigma=max(8.0, 2 * psf_radius))
    resid = img - level
    # each against the noise's sampling error and the noise model's own uncertainty
    scale_error = noise_scale_error(noise)
    for axis, name in ((1, "row_pattern"), (0, "column_pattern")):
        d = line_pattern(resid, level, free, noise, axis, scale_error)
        tests[name] = TestResult(name, d.pop("z"), th[name], d)
    d = window_structure(resid, level, free, noise, p, scale_error=scale_error)
    tests["background_structure"] = TestResult("background_structure", d.pop("z"),
                                               th["background_structure"], d)


def _amplitude_field_test(res, th, img, tests, k, flux):
    """Vignetting, or an off-centre illumination spot: a paraboloid of revolution with a
    free centre over the beads' amplitudes and their model-free fluxes; its z the smaller of
    the two."""
    if k >= 5:
        ok = (res.amplitude > 0) & (flux > 0)
        if ok.sum() >= 12:
            # vignetting / an off-centre illumination spot: a paraboloid of revolution
            # with a free centre, as the throughput is fitted (3 dof, not the full
            # quadratic's 5: fewer dof, more power, bench/bench_power.py). A throughput
            # shows in the model-free patch fluxes as much as in the fitted amplitudes;
            # a PSF model whose error grows towards the edge biases the amplitudes alone
            # (on still scenes of the family the amplitudes alone can exceed the
            # threshold where the fluxes do not). The test's z is the smaller of the two
            d_amp = radial_trend(res.positions[ok], res.amplitude[ok], img.shape,
                                  th["amplitude_field"])
            d_flux = radial_trend(res.positions[ok], flux[ok], img.shape,
                                   th["amplitude_field"])
            z = min(d_amp["z"], d_flux["z"])
            tests["amplitude_field"] = TestResult(
                "amplitude_field", z, th["amplitude_field"],
                {"F": d_amp["F"], "p": d_amp["p"], "z_amplitude": d_amp["z"],
                 "z_flux": d_flux["z"], "F_flux": d_flux["F"],
                 "min_corner_loss": d_amp["min_corner_loss"],
                 "coefficients": d_amp["coefficients"]})


def _saturation_test(res, psf_radius, all_positions, th, img, tests):
    """Pixels at the image's top in every detection's core: the beads left out as saturated
    are the ones that show it."""
    top = float(img.max())
    cores = np.zeros(img.shape, bool)
    # every detection's core: the beads left out as saturated are the ones that show it
    every = res.positions if all_positions is None else np.asarray(all_positions, float)
    iy = np.clip(np.round(every[:, 0]).astype(int), 0, img.shape[0] - 1)
    ix = np.clip(np.round(every[:, 1]).astype(int), 0, img.shape[1] - 1)
    cores[iy, ix] = True
    cores = ndi.binary_dilation(cores, iterations=max(1, int(psf_radius / 3)))
    n_top = int(np.count_nonzero((img >= top) & cores))
    tests["saturation"] = TestResult("saturation", float(n_top if n_top >= 2 else 0),
                                     th["saturation"], {"level": top, "pixels": n_top})
