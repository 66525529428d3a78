"""Does an effect help? The paired comparison of two cross-fits of the same beads, before
and after an effect, that the loop's acceptance rule reads: the change of the held-out
error and of the excess chi-square with bootstrap and permutation p-values, and for
throughput effects the held-out photometric error.
"""

from __future__ import annotations

import numpy as np

from ..beads.noise import NoiseModel
from .crossfit import CrossFit
from .photometry import (
    crossfit_log_residuals,
    trend_p_value,
)

#: Quantile at which the per-bead excess chi-square is winsorised in comparisons.
CHI2_WINSOR = 0.95
#: The excess chi-square's relative drop is taken against at least this many standard
#: errors of the mean excess (pure noise's, and the noise model's gain uncertainty).
CHI2_EXCESS_Z = 3.0


def _compare_photometry(before: CrossFit, after: CrossFit, shape: tuple[int, int],
                        throughput: tuple[int, int], flux: np.ndarray | None,
                        n_boot: int, seed: int) -> dict:
    """The held-out photometric error of two cross-fits of different throughputs (see
    :func:`compare`), on every bead whose brightness both measure."""
    r0, r1 = before.residuals, after.residuals
    # photometry judges every bead whose brightness is measured, not only those whose
    # shape informs the PSF (a faint field on a bright background: 1 of 148 beads)
    _, i0, i1 = np.intersect1d(before.bead_index, after.bead_index, return_indices=True)
    keep = r0.photometric[i0] & r1.photometric[i1]
    if flux is not None:
        keep &= np.asarray(flux)[i1] > 0
    i0, i1 = i0[keep], i1[keep]
    l0 = crossfit_log_residuals(r0.positions, r0.amplitude, before.fold, shape,
                                degree=throughput[0], use=r0.photometric)[i0]
    l1 = crossfit_log_residuals(r1.positions, r1.amplitude, after.fold, shape,
                                degree=throughput[1], use=r1.photometric)[i1]
    ok = np.isfinite(l0) & np.isfinite(l1)
    n = int(ok.sum())
    if n < 5:
        return {}
    q0, q1 = l0[ok] ** 2, l1[ok] ** 2
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(n_boot, n))
    m0, m1 = float(q0.mean()), float(q1.mean())
    p_held = float(np.mean(q1[idx].mean(axis=1) >= q0[idx].mean(axis=1)))
    # the size of the gain is the held-out drop; its significance the nested models'
    # permutation test on the same beads (the paired test of held-out squared errors
    # carries the beads' own brightness scatter twice and has about half the z,
    # bench/bench_power.py), see
    # :func:`~napari_psfspace.core.diagnosis.photometry.trend_p_value`. It must hold in the
    # model-free patch fluxes too: a PSF model whose error grows towards the edge
    # biases the fitted amplitudes radially by itself
    lo, hi = sorted(throughput)
    pos = r1.positions[i1][ok]
    trend = trend_p_value(pos, r1.amplitude[i1][ok], shape, degree0=lo, degree1=hi,
                          seed=seed)
    out = {"photometric_before": m0, "photometric_after": m1,
           "photometric_improvement": (m0 - m1) / m0 if m0 > 0 else 0.0,
           "photometric_p_no_drop": trend["p"], "photometric_p_heldout": p_held,
           "photometric_F": trend["F"], "photometric_n_beads": n}
    if flux is not None:
        tf = trend_p_value(pos, np.asarray(flux)[i1][ok], shape, degree0=lo, degree1=hi,
                           seed=seed)
        out.update(photometric_p_no_drop=max(trend["p"], tf["p"]),
                   photometric_p_amplitude=trend["p"], photometric_p_flux=tf["p"])
    return out


#: Fewest beads a paired comparison is made on; with fewer, no drop is measured.
MIN_PAIRED = 5


def paired_beads(before: CrossFit, after: CrossFit,
                 reference: np.ndarray | None = None, *, informative: bool = True
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The beads two cross-fits both judge informatively (and that are in ``reference``,
    bead table indices, when given): ``(bead index, entry in before, entry in after)``.

    Every figure of a diagnosis step (the error before, after and its drop) is a mean
    over these beads, so that the three are one quantity; with one ``reference`` (the
    plain model's informative beads) the figures of successive steps chain.
    ``informative=False``: every bead both judge (a scene where no bead is informative,
    as :meth:`~.residuals.BeadResiduals.summary` falls back to).
    """
    common, i0, i1 = np.intersect1d(before.bead_index, after.bead_index,
                                    return_indices=True)
    keep = np.ones(len(common), bool)
    if informative:
        keep &= before.residuals.informative[i0] & after.residuals.informative[i1]
    if reference is not None:
        keep &= np.isin(common, reference)
    return common[keep], i0[keep], i1[keep]


def paired_errors(before: CrossFit, after: CrossFit, noise: NoiseModel,
                  reference: np.ndarray | None = None, *, informative: bool = True) -> dict:
    """Mean held-out error and chi-square per dof of two cross-fits on the beads both
    judge (:func:`paired_beads`): ``error_before``, ``error_after``, ``chi2_before``,
    ``chi2_after``, ``noise_floor`` (``after``'s) and ``n_beads``; NaN without beads."""
    common, i0, i1 = paired_beads(before, after, reference, informative=informative)
    if len(common) == 0:
        nan = float("nan")
        return {"error_before": nan, "error_after": nan, "chi2_before": nan,
                "chi2_after": nan, "noise_floor": nan, "n_beads": 0}
    r0, r1 = before.residuals, after.residuals
    return {"error_before": float(r0.rel_energy[i0].mean()),
            "error_after": float(r1.rel_energy[i1].mean()),
            "chi2_before": float((r0.chi2_under(noise)[i0] / r0.dof[i0]).mean()),
            "chi2_after": float((r1.chi2_under(noise)[i1] / r1.dof[i1]).mean()),
            "noise_floor": float(r1.floor[i1].mean()), "n_beads": int(len(common))}


def compare(before: CrossFit, after: CrossFit, noise: NoiseModel, n_boot: int = 1000,
             seed: int = 0, *, shape: tuple[int, int] | None = None,
             throughput: tuple[int, int] = (0, 0), flux: np.ndarray | None = None,
             reference: np.ndarray | None = None, informative: bool = True) -> dict:
    """Paired comparison of two cross-fits on the informative beads both judge
    (:func:`paired_beads`; restricted to ``reference`` when given).

    ``error_before``, ``error_after`` and ``improvement`` (``1 - after / before``) are
    means over the same beads; ``chi2_before`` and ``chi2_after`` the beads' mean chi-square
    per dof under ``noise``. With fewer than :data:`MIN_PAIRED` such beads nothing is
    measured: the errors are those beads' (or NaN), ``improvement`` is NaN and
    ``p_no_drop`` 1, and ``note`` says why.

    Two held-out metrics, each averaged over beads: the relative residual energy
    (signal-normalised: PSF shape) and the excess chi-square per dof, ``chi2/dof - 1``
    (noise-normalised: also sees misfit in the faint wings and background, e.g. camera
    offsets), both cross-fits judged under the same noise model ``noise`` (the newer
    one: photon transfer on an uncorrected image counts camera patterns as noise; values
    above the :data:`CHI2_WINSOR` quantile of both are clipped to it). For
    each, the relative drop and the bootstrap probability (over beads, paired) that it
    did not drop.

    When the two models' throughputs differ (``throughput``: degrees before and after,
    :mod:`~napari_psfspace.core.diagnosis.photometry`), a third metric is compared: the held-out
    photometric error, each bead's squared log ratio of measured to predicted amplitude.
    Its drop is the held-out one; its significance (``photometric_p_no_drop``) is the
    nested throughputs' permutation test on the same beads
    (:func:`~napari_psfspace.core.diagnosis.photometry.trend_p_value`), in the fitted amplitudes
    and, when ``flux`` (model-free patch fluxes of ``after``'s beads) is given, in
    those too (the larger p); the held-out paired bootstrap's is kept as
    ``photometric_p_heldout``.
    """
    photometry = (_compare_photometry(before, after, shape, throughput, flux, n_boot, seed)
                  if shape is not None and throughput[0] != throughput[1] else {})
    common, i0, i1 = paired_beads(before, after, reference, informative=informative)
    shown = paired_errors(before, after, noise, reference, informative=informative)
    if len(common) < MIN_PAIRED:
        return {**shown, "improvement": float("nan"), "p_no_drop": 1.0,
                "chi2_improvement": float("nan"), "chi2_p_no_drop": 1.0,
                "note": f"not compared: {len(common)} bead(s) judged informatively by both "
                        f"models, need {MIN_PAIRED}", **photometry}
    r0, r1 = before.residuals, after.residuals
    e0, e1 = r0.rel_energy[i0], r1.rel_energy[i1]
    c0 = r0.chi2_under(noise)[i0] / r0.dof[i0] - 1.0
    c1 = r1.chi2_under(noise)[i1] / r1.dof[i1] - 1.0
    # a handful of beads with an extreme chi-square (a cosmic ray, a bead on a dust
    # particle) would decide the mean alone: both are winsorised at the same level
    top = float(np.quantile(np.concatenate([c0, c1]), CHI2_WINSOR))
    c0, c1 = np.minimum(c0, top), np.minimum(c1, top)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(common), size=(n_boot, len(common)))

    def drop(a, b, floor=0.0, excess=False):
        ma, mb = float(a.mean()), float(b.mean())
        if excess:  # an excess below zero is noise: no model can drop it further
            ma, mb = max(ma, 0.0), max(mb, 0.0)
        base = max(abs(ma), floor)
        rel = (ma - mb) / base if base != 0 else 0.0
        return rel, float(np.mean(b[idx].mean(axis=1) >= a[idx].mean(axis=1)))

    imp, p = drop(e0, e1)
    # the mean is led by the few beads farthest from their noise floor, and so is its
    # bootstrap: an effect that helps most beads a little can read as not significant
    # (a weak compressive response, bench/bench_diagnose.py). The typical bead's
    # relative change, the mean log ratio, is a second, robust test of the same drop
    tiny = 1e-300
    lr = np.log(np.maximum(e1, tiny) / np.maximum(e0, tiny))
    p_log = float(np.mean(lr[idx].mean(axis=1) >= 0.0))
    # an excess chi-square within its own uncertainty is no excess: relative to it, any
    # change reads as a large relative drop (a model at its noise floor). Two sources:
    # the mean of pure noise's chi2/dof (sd sqrt(2 / dof) per bead), and the noise
    # model's own relative error (a gain known to 5 % puts the "1" of chi2/dof - 1 within
    # about 0.05)
    se_noise = float(np.sqrt(2.0 / np.mean(r0.dof[i0]) / len(common)))
    se_model = float((noise.checks or {}).get("gain_relative_error", 0.0) or 0.0)
    chi2_noise = CHI2_EXCESS_Z * float(np.hypot(se_noise, se_model))
    cimp, cp = drop(c0, c1, floor=chi2_noise, excess=True)
    # the paired difference's standard error: how far the after can sit above the
    # before by the beads' scatter alone (a correction's "not worse")
    se = float(np.std(e1 - e0, ddof=1) / np.sqrt(len(common)))
    out = {**shown, "improvement": imp, "p_no_drop": min(p, p_log), "p_mean": p,
           "error_se": se,
           "p_log_ratio": p_log, "median_ratio": float(np.exp(np.median(lr))),
           "chi2_improvement": cimp,
           "chi2_p_no_drop": cp, "n_beads": int(len(common))}
    out.update(photometry)
    return out
