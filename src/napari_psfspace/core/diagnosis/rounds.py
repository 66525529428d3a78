"""The rounds of the diagnosis loop (:mod:`.loop`): the beads and the noise model it
starts from, one cross-fit and analysis of a model, the plain model's baseline, the
hot-pixel masking as a step, the effects tried one at a time, and the final operator.

Each round is a generator of :class:`~napari_psfspace.core.common.progress.Progress`
records (a point to cancel at) returning its result; the steps it decides are appended
to the diagnosis's list of :class:`~.steps.Step`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..beads.centering import refine_centers
from ..beads.detect import Beads, detect_beads, flag_unusable
from ..beads.noise import NoiseModel, noise_model
from ..common.progress import Progress, check_halt
from ..common.spacing import bead_border, centring_sigma
from ..common.validate import as_image
from ..model.estimate import iter_estimate
from ..model.operator import ProductConvolution
from .acceptance import accept_effect, evident_tests, kept_by_own_test, next_effect, own_statistic
from .analysis import analyse
from .bead_tests import bead_flux
from .comparison import compare, paired_errors
from .corrections import hot_pixel_step, motion_step, spike_count
from .crossfit import CrossFit, iter_crossfit
from .effects import Context, Effect
from .metric import HeldoutError
from .photometry import fit_throughput, throughput_map
from .steps import Step


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


def evaluate(c: Context, stage: str, fraction: float, *, psf_radius: float, folds: int):
    """Cross-fit the model of ``c`` on its beads and analyse the held-out residuals;
    returns the cross-fit and the analysis, its tests' beads as bead-table indices."""
    r = psf_radius
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


def baseline_round(ctx: Context, evaluate: Callable, noise_source: str):
    """The plain model's step. Every figure of the diagnosis is a mean over its
    informative beads (those each compared model judges too; else every bead), so that
    the figures of successive steps chain. Returns the context with the model's record,
    its cross-fit and analysis, the held-out error, the steps so far and the beads that
    judge (``reference`` and ``informative`` of :func:`~.comparison.paired_errors`)."""
    cf, an = yield from evaluate(ctx, "baseline", 0.1)
    ctx = ctx.with_effect("_model", cf.model_meta) if cf.model_meta else ctx
    noise = ctx.noise
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
    return ctx, cf, an, held, steps, {"reference": reference, "informative": informative}


def hot_pixel_round(ctx: Context, cf: CrossFit, an, raw: np.ndarray, recorded: np.ndarray,
                    judge: dict, steps: list[Step], evaluate: Callable):
    """The masking at detection as a step: the image as recorded against the masked
    one; the recorded image's context, cross-fit and analysis where masking does not
    lower the held-out error, and the hot pixels masked (None where the masking is not
    kept)."""
    hot, beads, img, noise = ctx.pixel_mask, ctx.beads, ctx.image, ctx.noise
    reference, informative = judge["reference"], judge["informative"]
    masked = beads.hot_pixels
    if hot.any():  # the masking at detection, as a step: the image as recorded before
        raw_ctx = replace(ctx, image=recorded, pixel_mask=np.zeros_like(hot))
        raw_cf, raw_an = yield from evaluate(raw_ctx, "hot pixels", 0.15)
        step = hot_pixel_step(raw_cf, cf, noise, reference, informative=informative,
                              spikes_before=len(beads.hot_pixels),
                              spikes_after=spike_count(img, raw))
        steps.append(step)
        if not step.accepted:  # the recorded image it is
            ctx, cf, an, masked = raw_ctx, raw_cf, raw_an, None
        yield Progress("hot pixels", 0.2, f"{step.params['count']} hot pixel(s): error "
                       f"{step.error_before:.4g} -> {step.error_after:.4g}, "
                       f"{'masked' if step.accepted else 'left'}")
    return ctx, cf, an, masked


def effect_rounds(ctx: Context, cf: CrossFit, an, candidates: list[Effect], judge: dict,
                  steps: list[Step], evaluate: Callable, *, max_steps: int,
                  min_improvement: float, evident_improvement: float, max_p: float,
                  explore: float):
    """The effects, strongest evidence first, each fitted, applied and cross-fitted
    again, kept only where the held-out error drops (:mod:`.loop`); returns the context,
    cross-fit and analysis of the last model kept."""
    reference, informative = judge["reference"], judge["informative"]
    r, shape = ctx.psf_radius, ctx.image.shape
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
        cmp = compare(cf, new_cf, new_ctx.noise, shape=shape, throughput=throughput,
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
    return ctx, cf, an


def final_round(ctx: Context, cf: CrossFit, first_cf: CrossFit, judge: dict,
                steps: list[Step], *, bead_diameter: float, remove_motion: bool):
    """The final operator: a point source's PSFs when the beads' size is known (the
    nominal one, which the bead-size effect then takes for the median bead's); its
    held-out split, as the Model step's, measures its error for the deblur's weights
    and compression (without it a deblur takes the model for exact). Returns the
    figures of the whole diagnosis and the operator."""
    r = ctx.psf_radius
    reference, informative = judge["reference"], judge["informative"]
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
    return total, op
