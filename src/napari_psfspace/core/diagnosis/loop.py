"""Close the loop on measured data: fit, analyse residuals, add what the model lacks.

``diagnose(image, psf_radius=...)``:

1. Detect and centre the beads; estimate the noise model from the image (or take the
   camera's gain, offset and read noise).
2. Cross-fit (:mod:`~napari_psfspace.core.diagnosis.crossfit`): each bead's residual comes from a
   model estimated without it; the pooled relative residual energy of all beads is the
   model's held-out error.
3. Analyse the residuals (:mod:`~napari_psfspace.core.diagnosis.analysis`), rank the candidate
   effects (:mod:`~napari_psfspace.core.diagnosis.effects`) by evidence, fit the strongest, apply
   it, cross-fit again.
4. Keep the effect only if a held-out error drops significantly on the beads both
   models judge: the mean relative residual energy (PSF shape) or the mean excess
   chi-square per dof (noise-normalised: faint wings, background, camera), by at least
   ``min_improvement`` (relative; ``evident_improvement`` for an effect whose own test
   is significant) and with a paired bootstrap over beads giving a
   probability below ``max_p / 2`` that it did not drop, while neither metric gets worse
   by ``min_improvement`` (for a change of throughput, the held-out photometric error
   counts too, its significance from the nested throughputs' permutation test). The
   excess chi-square's drop is relative to at least its own
   uncertainty (:data:`~.comparison.CHI2_EXCESS_Z` standard errors: the noise's, and the noise
   model's own relative error), and it does not decide under an assumed
   noise model (a fallback: no shot noise measured). Repeat with the next candidate
   until none has evidence left; while a residual common to the beads remains far
   above the noise, candidates with weaker evidence (above ``explore`` times their
   threshold) are tried as well, under the same rule. An effect with a test of its own
   that reads its correction (:attr:`~.effects.base.Effect.own_evidence`: a detector
   response, camera line offsets, outlier pixels) is also kept when that
   test goes from significant to not and the held-out error is not worse by more than
   one standard error of the paired difference (no held-out error can see such an
   effect when the learnt PSF absorbs it).
5. Estimate the final operator on all beads with the effects kept.
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..beads.centering import refine_centers
from ..beads.detect import (
    DETECTION_ADVICE,
    GIVEN_ADVICE,
    Beads,
    detect_beads,
    flag_unusable,
    require_kept,
)
from ..beads.noise import NoiseModel, noise_model
from ..beads.saturation import saturation_record
from ..beads.spikes import spike_mask
from ..common.progress import Progress, check_halt
from ..common.spacing import bead_border, centring_sigma
from ..common.threads import blas_threads
from ..common.twins import drained
from ..common.validate import as_array, as_image, check_camera, check_psf_radius
from ..model.estimate import check_bead_diameter, hot_pixel_record, iter_estimate
from ..model.operator import ProductConvolution
from .acceptance import (
    accept_effect,
    evident_tests,
    kept_by_own_test,
    next_effect,
    own_statistic,
)
from .analysis import Analysis, analyse
from .bead_tests import bead_flux
from .comparison import compare, paired_errors
from .corrections import hot_pixel_step, motion_step, spike_count
from .crossfit import CrossFit, iter_crossfit
from .effects import REGISTRY, Context, Effect
from .metric import HeldoutError
from .photometry import (
    fit_throughput,
    throughput_map,
)
from .steps import Step

#: The float64 images of the image's size the diagnosis holds at once (its estimates on
#: each fold, their model images and residuals), as float32 images with a margin: its
#: memory is checked first.
DIAGNOSE_IMAGES = 32

#: Fewest usable beads a diagnosis runs on; below ``2 folds`` beads it holds out one bead
#: at a time (leave-one-bead-out).
MIN_BEADS = 5



@dataclass
class Diagnosis:
    """Result of :func:`diagnose`.

    Attributes
    ----------
    steps : list of Step
        The baseline, then every effect tried, in order.
    error_before, error_after : float
        Held-out (cross-fitted) relative residual energy of the plain model and of the
        final one: means over the same :attr:`n_beads` beads (the plain model's
        informative beads that the final model judges too), as every step's figures.
    chi2_before, chi2_after : float
        Mean chi-square per degree of freedom of those beads under the noise model.
    noise_floor : float
        The error noise alone would leave on those beads (the final model's fits).
    n_beads : int
        The beads the figures are means over.
    operator : ProductConvolution
        The refined model, estimated on all beads with the effects kept.
    context : Context
        The final model context (corrected image, masks, options).
    noise_source : str
        How the noise model was obtained.
    masked_pixels : ndarray of shape (S, 2) or None
        The hot pixels found at detection (see :attr:`hot_pixels`).
    heldout : HeldoutError or None
        The plain model's held-out error on all its informative beads
        (:mod:`~napari_psfspace.core.diagnosis.metric`): the figure every report gives
        for the model before the diagnosis (:func:`iter_heldout_error` computes the same).
    """

    steps: list[Step]
    error_before: float
    error_after: float
    chi2_before: float
    chi2_after: float
    noise_floor: float
    operator: ProductConvolution
    context: Context
    analysis_before: Analysis
    analysis_after: Analysis
    crossfit_before: CrossFit
    crossfit_after: CrossFit
    noise_source: str
    options: dict = field(default_factory=dict)
    masked_pixels: np.ndarray | None = None
    n_beads: int = 0
    heldout: HeldoutError | None = None

    @property
    def added(self) -> list[str]:
        """Names of the effects kept."""
        return [s.effect for s in self.steps if s.effect and s.accepted]

    @property
    def verdict(self):
        """Whether the final model explains its held-out beads
        (:class:`~napari_psfspace.core.diagnosis.verdict.Verdict`): the first line of
        every report."""
        from .verdict import verdict

        return verdict(self)

    @property
    def hot_pixels(self) -> np.ndarray:
        """``(row, column)`` of the pixels masked at detection as narrower than the optics
        can form (hot pixels, cosmic rays), shape (S, 2)."""
        hot = self.masked_pixels
        return np.zeros((0, 2), np.int64) if hot is None else hot

    def to_dict(self) -> dict:
        return {
            "error_before": self.error_before, "error_after": self.error_after,
            "chi2_dof_before": self.chi2_before, "chi2_dof_after": self.chi2_after,
            "noise_floor": self.noise_floor, "n_beads": self.n_beads,
            "heldout_error": None if self.heldout is None else self.heldout.to_dict(),
            "verdict": self.verdict.to_dict(), "added": self.added, "options": self.options,
            "noise_model": {**self.context.noise.to_dict(), "source": self.noise_source},
            "hot_pixels": hot_pixel_record(self.hot_pixels),
            "steps": [s.to_dict() for s in self.steps],
            "analysis_before": self.analysis_before.to_dict(),
            "analysis_after": self.analysis_after.to_dict(),
        }


def prepare_beads(image: np.ndarray, psf_radius: float, *, threshold: float = 8.0,
                  beads: Beads | None = None) -> Beads:
    """Detected beads (or a copy of ``beads``: the user's table, whose statuses, such as
    the beads rejected by hand, are kept) with sub-pixel centres and their status (kept,
    border, ...)."""
    if beads is None:
        beads = detect_beads(image, psf_radius, threshold=threshold)
    else:
        beads = Beads(np.array(beads.positions, float), np.array(beads.response, float),
                      np.array(beads.status), np.array(beads.amplitude, float),
                      None if beads.hot_pixels is None else np.array(beads.hot_pixels))
    img = beads.clean_image(as_image(image))
    kept = beads.kept
    beads.positions[kept] = refine_centers(img, beads.positions[kept],
                                           sigma=centring_sigma(psf_radius),
                                           half=int(np.ceil(psf_radius)))
    flag_unusable(beads, img, psf_radius, saturation=None,
                  border=bead_border(psf_radius))
    return beads


def noise_model_with_source(image, gain, offset, read_noise, mask=None) -> tuple[NoiseModel, str]:
    noise = noise_model(image, mask=mask, gain=gain, offset=offset, read_noise=read_noise)
    source = {"camera": "camera values given", "photon transfer": "photon transfer on the image"
              }.get(noise.kind, f"{noise.kind} (fallback: {noise.note})")
    return noise, source


def forward(gen, stage: str, fraction: float):
    """Run a sub-generator, passing its messages on at ``fraction`` (each of its yields is
    a point to cancel at); return its value."""
    while True:
        try:
            p = next(gen)
        except StopIteration as done:
            return done.value
        yield Progress(stage, fraction, p.message)


def final_operator(operator: ProductConvolution, ctx: Context, cf: CrossFit,
                   added: list[str], total: dict) -> ProductConvolution:
    """The refined operator with the diagnosis in its metadata: the reference bead size
    when the bead-size effect was kept, and the throughput (vignetting) fitted on the
    last cross-fit's photometric beads folded into its maps."""
    def finite(v):
        return float(v) if np.isfinite(v) else None

    shape = ctx.image.shape
    meta = {**operator.metadata, "diagnosis": {"added": added,
                                               "error_before": finite(total["error_before"]),
                                               "error_after": finite(total["error_after"]),
                                               "noise_floor": finite(total["noise_floor"]),
                                               "n_beads": total["n_beads"]}}
    coefficients = operator.coefficients
    if "bead_size" in ctx.params:  # the PSFs are those of a bead of the reference size
        meta["bead_size"] = {"d_ref_px": ctx.params["bead_size"].get("d_ref_px")}
    if ctx.throughput_degree > 0:
        res = cf.residuals
        use = res.photometric
        tcoef = fit_throughput(res.positions[use], res.amplitude[use], shape,
                               degree=ctx.throughput_degree)
        grid = operator.grid
        gy, gx = grid if grid is not None else (np.arange(shape[0]), np.arange(shape[1]))
        coefficients = coefficients * throughput_map(tcoef, gy, gx, shape)[None]
        meta["throughput"] = {"model": "exp(polynomial of u, v)", "degree":
                              ctx.throughput_degree, "coefficients": tcoef.tolist(),
                              "normalisation": "mean over the field = 1"}
    return ProductConvolution(operator.basis, coefficients, shape=operator.image_shape,
                              grid=operator.grid, metadata=meta)


@blas_threads
def iter_diagnose(
    image,
    *,
    psf_radius: float,
    threshold: float = 8.0,
    gain: float | None = None,
    offset: float | None = None,
    read_noise: float | None = None,
    folds: int = 5,
    effects: Sequence[str] | None = None,
    max_steps: int = 8,
    min_improvement: float = 0.05,
    evident_improvement: float = 0.02,
    max_p: float = 0.01,
    explore: float = 0.5,
    n_psf: int | None = None,
    smoothing: float | None = None,
    bead_diameter: float = 0.0,
    remove_motion: bool = False,
    beads: Beads | None = None,
    _baseline_only: bool = False,  # return the plain model's held-out error (iter_heldout_error)
) -> Generator[Progress, None, Diagnosis]:
    """Fit, trace the held-out residual to what the model lacks, add it, report.

    Parameters
    ----------
    image : array_like of shape (M, N)
        Raw bead image in ADU (not rescaled: the noise model is estimated from it).
    psf_radius : float
        PSF radius in pixels.
    threshold : float
        Detection threshold (noise sd of the filtered image).
    gain, offset, read_noise : float, optional
        Camera values (ADU/e-, ADU, e-); default: photon transfer on the image.
    folds : int
        Cross-fitting folds (5: each fold is a spatially spread 20 % hold-out). With
        fewer than ``2 folds`` usable beads (but at least :data:`MIN_BEADS`), each bead
        is held out on its own (leave-one-bead-out).
    effects : sequence of str, optional
        Effects to consider (default: all of
        :data:`~napari_psfspace.core.diagnosis.effects.REGISTRY`).
    max_steps : int
        Most effects tried.
    min_improvement : float
        Smallest relative drop of the held-out error for an effect to be kept.
    evident_improvement : float
        The smallest drop instead, for an effect whose own residual test is significant
        (evidence > 1; those tried only while exploring need ``min_improvement``).
    max_p : float
        Largest bootstrap probability that the error did not drop.
    n_psf, smoothing : optional
        The model to diagnose: basis size and thin-plate smoothing (default: chosen from
        the beads, as :func:`~napari_psfspace.core.model.estimate.estimate_operator` does).
    bead_diameter : float
        The beads' diameter in pixels, when known (0: point sources). Beads are judged on
        their own images; the refined operator has the sphere divided out (as
        :func:`~napari_psfspace.core.model.estimate.estimate_operator` does), and the
        bead-size effect takes it for the median bead's diameter.
    remove_motion : bool
        Motion blur is looked for in the final model and reported (``metadata["motion"]``;
        it is common to every bead, so no held-out error can see it); True divides the
        smear found out of the refined operator's PSFs
        (:func:`~napari_psfspace.core.model.estimate.estimate_operator`).
    explore : float
        While a residual common to the beads is left (``mean_residual`` or
        ``coherent_residual`` significant) and the held-out error exceeds 1.5 times the
        noise floor, effects with evidence above this fraction of their threshold are
        tried too (kept only by the same rule); 0 tries significant evidence only.
    beads : Beads, optional
        The user's bead table (e.g. edited in napari: beads rejected by hand keep that
        status and are not used); None detects them at ``threshold``.

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    Diagnosis
        ``.steps``, ``.error_before``, ``.error_after``, ``.operator`` (refined model).
    """
    raw = np.asarray(as_array(image, "image"))
    img = as_image(raw, dtype=np.float64, copies=DIAGNOSE_IMAGES)
    r = check_psf_radius(psf_radius, img.shape)
    bead_diameter = check_bead_diameter(bead_diameter, r)
    gain, offset, read_noise, _ = check_camera(gain, offset, read_noise)
    if gain is None and (offset is not None or read_noise is not None):
        raise ValueError("`offset` and `read_noise` describe the camera with `gain`: give "
                         "`gain` too, or none of them (the noise model is then measured)")
    if isinstance(folds, (bool, np.bool_)) or not isinstance(folds, (int, np.integer)) \
            or folds < 2:
        raise ValueError(f"`folds` must be a whole number >= 2 (cross-fitting folds), got "
                         f"{folds!r}")
    names = list(REGISTRY) if effects is None else list(effects)
    unknown = [n for n in names if n not in REGISTRY]
    if unknown:
        raise ValueError(f"Unknown effect(s) {unknown}; known: {sorted(REGISTRY)}.")
    candidates: list[Effect] = [REGISTRY[n]() for n in names]

    given = beads is not None
    beads = prepare_beads(raw, r, threshold=threshold, beads=beads)
    n_kept = int(np.count_nonzero(beads.kept))
    if n_kept < 2 * folds:  # few beads: each is judged by a model of all the others
        require_kept(beads, MIN_BEADS, reason="to judge each bead by a model learnt "
                     "without it (leave-one-bead-out)",
                     advice=GIVEN_ADVICE if given else DETECTION_ADVICE)
        folds = n_kept
    hot = spike_mask(img.shape, beads.hot_pixels)
    recorded = img
    img = beads.clean_image(img)
    noise, noise_source = noise_model_with_source(raw, gain, offset, read_noise, mask=hot)
    model = {k: v for k, v in (("n_psf", n_psf), ("smoothing", smoothing)) if v is not None}
    ctx = Context(image=img, pixel_mask=hot, beads=beads, noise=noise,
                  psf_radius=r, noise_from_image=gain is None, estimate_kwargs=model,
                  bead_diameter=bead_diameter)
    yield Progress("prepare", 0.05, f"{beads.summary()}; noise model: {noise_source}")

    def evaluate(c: Context, stage: str, fraction: float):
        cf = yield from forward(iter_crossfit(c.image, c.beads, c.noise, psf_radius=r,
                                              folds=folds, estimate_kwargs=c.estimate_kwargs,
                                              fit_kwargs={**c.fit_kwargs,
                                                          "pixel_mask": c.pixel_mask}),
                                stage, fraction)
        check_halt()
        an = analyse(cf.residuals, c.image, c.noise, psf_radius=r,
                     all_positions=c.beads.positions)
        for name in ("secondary_peaks", "elongated_beads"):
            sp = an.tests.get(name)
            if sp is not None:  # residual entries -> bead table indices
                sp.detail["bead_index"] = cf.bead_index[
                    np.asarray(sp.detail["beads"], int)].tolist()
        return cf, an

    cf, an = yield from evaluate(ctx, "baseline", 0.1)
    ctx = ctx.with_effect("_model", cf.model_meta) if cf.model_meta else ctx
    first_cf, first_an = cf, an
    # every figure of the diagnosis is a mean over the plain model's informative beads
    # (those each compared model judges too): the figures of successive steps chain
    informative = bool(cf.residuals.informative.any())  # else every bead, as summary()
    reference = cf.bead_index[cf.residuals.informative] if informative else cf.bead_index
    base = paired_errors(cf, cf, noise, reference, informative=informative)
    steps = [Step(effect=None, evidence=0.0, tests=[t.name for t in an.significant()],
                  error_before=base["error_before"], error_after=base["error_before"],
                  chi2_before=base["chi2_before"], chi2_after=base["chi2_before"],
                  improvement=0.0, p_no_drop=1.0, accepted=True,
                  params={"n_beads": base["n_beads"]})]
    held = HeldoutError(base["error_before"], base["noise_floor"], base["chi2_before"],
                        base["n_beads"], noise_source)
    yield Progress("baseline", 0.2, f"{held.line()}; misfit / noise {held.chi2_dof:.3g}")
    if _baseline_only:
        return held
    if hot.any():  # the masking at detection, as a step: the image as recorded before
        raw_ctx = replace(ctx, image=recorded, pixel_mask=np.zeros_like(hot))
        raw_cf, raw_an = yield from evaluate(raw_ctx, "hot pixels", 0.15)
        step = hot_pixel_step(raw_cf, cf, noise, reference, informative=informative,
                              spikes_before=len(beads.hot_pixels),
                              spikes_after=spike_count(img, raw))
        steps.append(step)
        if not step.accepted:  # the recorded image it is
            ctx, cf, an = raw_ctx, raw_cf, raw_an
            first_cf, first_an = cf, an
        yield Progress("hot pixels", 0.2, f"{step.params['count']} hot pixel(s): error "
                       f"{step.error_before:.4g} -> {step.error_after:.4g}, "
                       f"{'masked' if step.accepted else 'left'}")
    tried: set[str] = set()
    for k in range(max_steps):
        chosen = next_effect(candidates, tried, ctx, cf, an, explore)
        if chosen is None:
            break
        ev, eff = chosen
        tried.add(eff.name)
        try:
            check_halt()
            params = eff.fit(ctx, an)
            check_halt()
            new_ctx = eff.apply(ctx, params)
            new_cf, new_an = yield from evaluate(new_ctx, "effect",
                                                 min(0.9, 0.2 + 0.1 * k))
        except ValueError as exc:  # e.g. too few beads left to learn from: not kept
            s0 = paired_errors(cf, cf, ctx.noise, reference, informative=informative)
            steps.append(Step(effect=eff.name, evidence=float(ev), tests=evident_tests(eff, an),
                              error_before=s0["error_before"], error_after=s0["error_before"],
                              chi2_before=s0["chi2_before"], chi2_after=s0["chi2_before"],
                              improvement=float("nan"), p_no_drop=1.0, accepted=False,
                              params={"_error": str(exc), "n_beads": s0["n_beads"]}))
            yield Progress("effect", min(0.9, 0.2 + 0.1 * (k + 1)),
                           f"{eff.name}: could not be applied ({exc}), rejected")
            continue
        throughput = (ctx.throughput_degree, new_ctx.throughput_degree)
        flux = (bead_flux(new_ctx.image, new_cf.residuals.positions, r)
                if throughput[0] != throughput[1] else None)
        cmp = compare(cf, new_cf, new_ctx.noise, shape=img.shape, throughput=throughput,
                       flux=flux, reference=reference, informative=informative)
        ok = accept_effect(cmp, new_ctx.noise.kind, ev, min_improvement=min_improvement,
                           evident_improvement=evident_improvement, max_p=max_p)
        own = own_statistic(eff, an, new_an, new_ctx, new_cf)
        by_own = not ok and kept_by_own_test(eff, own, cmp, new_ctx.noise.kind,
                                             min_improvement=min_improvement)
        ok = ok or by_own
        # the step's figures are the decision's: the model before and after it on the
        # same beads (the plain model's informative beads both judge), so that before,
        # after and the drop are one quantity and each step starts where the last kept
        # one ended
        err0, err1 = cmp["error_before"], cmp["error_after"]
        steps.append(Step(effect=eff.name, evidence=float(ev), tests=evident_tests(eff, an),
                          error_before=err0, error_after=err1,
                          chi2_before=cmp["chi2_before"], chi2_after=cmp["chi2_after"],
                          improvement=float(cmp["improvement"]), p_no_drop=cmp["p_no_drop"],
                          accepted=ok,
                          params={**new_ctx.params.get(eff.name, params), "_comparison": cmp,
                                  **({"_kept_by": "its own test"} if by_own else {})},
                          statistic=own))
        if ok:
            ctx, cf, an = new_ctx, new_cf, new_an
            if cf.model_meta:
                ctx = ctx.with_effect("_model", cf.model_meta)
        drop = ("not compared: " + cmp["note"].split(": ", 1)[-1] if "note" in cmp
                else f"{-100 * cmp['improvement']:+.1f} %, excess chi2 "
                     f"{-100 * cmp['chi2_improvement']:+.1f} %")
        yield Progress("effect", min(0.9, 0.2 + 0.1 * (k + 1)),
                       f"{eff.name}: error {err0:.4g} -> {err1:.4g} on {cmp['n_beads']} "
                       f"beads ({drop}), {'kept' if ok else 'rejected'}")

    # the final operator: a point source's PSFs when the beads' size is known (the
    # nominal one, which the bead-size effect then takes for the median bead's); its
    # held-out split, as the Model step's, measures its error for the deblur's weights
    # and compression (without it a deblur took the model for exact)
    est = yield from forward(iter_estimate(ctx.image, psf_radius=r, beads=ctx.beads,
                                           holdout=0.2, bead_diameter=bead_diameter,
                                           remove_motion=remove_motion,
                                           **ctx.estimate_kwargs), "final", 0.95)
    total = paired_errors(first_cf, cf, ctx.noise, reference, informative=informative)
    motion = est.operator.metadata.get("motion") or {}
    if motion.get("detected"):  # a smear common to every bead, as a step of its own
        steps.append(motion_step(motion, bool(remove_motion), total["error_after"],
                                 total["chi2_after"], total["n_beads"]))
    added = [s.effect for s in steps if s.effect and s.accepted]
    op = final_operator(est.operator, ctx, cf, added, total)
    yield Progress("final", 1.0, f"added: {', '.join(added) or 'nothing'}")
    masked = None if any(s.effect == "hot_pixels" and not s.accepted for s in steps) \
        else beads.hot_pixels
    options = {"folds": folds, "leave_one_bead_out": folds == n_kept,
               "min_improvement": min_improvement,
               "evident_improvement": evident_improvement, "max_p": max_p,
               "explore": explore, "n_psf": n_psf, "smoothing": smoothing,
               "max_steps": max_steps, "threshold": threshold, "psf_radius": r,
               "bead_diameter": bead_diameter, "remove_motion": remove_motion,
               "effects": names,
               "saturation": saturation_record(raw, beads, r, None)}
    return Diagnosis(steps=steps, error_before=total["error_before"],
                     error_after=total["error_after"], chi2_before=total["chi2_before"],
                     chi2_after=total["chi2_after"], noise_floor=total["noise_floor"],
                     operator=op, context=ctx, analysis_before=first_an, analysis_after=an,
                     crossfit_before=first_cf, crossfit_after=cf, noise_source=noise_source,
                     options=options, masked_pixels=masked,
                     n_beads=total["n_beads"], heldout=held)


def iter_heldout_error(image, *, psf_radius: float, **kwargs
                       ) -> Generator[Progress, None, HeldoutError]:
    """The held-out error of the plain model on an image's beads
    (:mod:`~napari_psfspace.core.diagnosis.metric`): the diagnosis's baseline, by the
    same code, so that the Model step, ``psfspace estimate``, Diagnose and the report
    give one number for one image and beads.

    Parameters
    ----------
    image : array_like of shape (M, N)
    psf_radius : float
        Pixels.
    **kwargs
        ``threshold``, ``gain``, ``offset``, ``read_noise``, ``folds``, ``n_psf``,
        ``smoothing``, ``bead_diameter``, ``beads`` of :func:`iter_diagnose`.

    Returns
    -------
    HeldoutError
    """
    return (yield from iter_diagnose(image, psf_radius=psf_radius, effects=[],
                                     max_steps=0, _baseline_only=True, **kwargs))


diagnose = drained(iter_diagnose, "diagnose")
