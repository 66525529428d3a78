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
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from ..beads.detect import (
    DETECTION_ADVICE,
    GIVEN_ADVICE,
    Beads,
    require_kept,
)
from ..beads.saturation import saturation_record
from ..beads.spikes import spike_mask
from ..common.progress import Progress
from ..common.threads import blas_threads
from ..common.twins import drained
from ..common.validate import as_array, as_image, check_camera, check_psf_radius
from ..model.estimate import check_bead_diameter
from ..model.estimate_record import hot_pixel_record
from ..model.operator import ProductConvolution
from .analysis import Analysis
from .crossfit import CrossFit
from .effects import REGISTRY, Context
from .metric import HeldoutError
from .rounds import (
    baseline_round,
    effect_rounds,
    evaluate,
    final_round,
    hot_pixel_round,
    noise_model_with_source,
    prepare_beads,
)
from .steps import Step

#: The float64 images of the image's size the diagnosis holds at once (its estimates on
#: each fold, their model images and residuals), as float32 images with a margin: its
#: memory is checked first.
DIAGNOSE_IMAGES = 32

#: The figures of a diagnosis as a whole, from the first model's and the last one's
#: held-out residuals on the same beads (:func:`~.comparison.paired_errors`).
FIGURES = ("error_before", "error_after", "chi2_before", "chi2_after", "noise_floor",
           "n_beads")

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
        Cross-fitting folds, each a spatially spread hold-out; below ``2 folds`` usable
        beads (and at least :data:`MIN_BEADS`), one bead at a time (leave-one-bead-out).
    effects : sequence of str, optional
        Effects to consider (default: all of :data:`~.effects.REGISTRY`).
    max_steps : int
        Most effects tried.
    min_improvement : float
        Smallest relative drop of the held-out error for an effect to be kept.
    evident_improvement : float
        The smallest drop instead for an effect whose own residual test is significant.
    max_p : float
        Largest bootstrap probability that the error did not drop.
    n_psf, smoothing : optional
        The model's basis size and thin-plate smoothing (default: chosen from the beads).
    bead_diameter : float
        The beads' diameter in pixels when known (0: point sources); the refined operator
        has the sphere divided out, the bead-size effect takes it for the median bead's.
    remove_motion : bool
        Divide the motion smear found in the final model out of its PSFs (it is reported
        either way, ``metadata["motion"]``: no held-out error sees a smear every bead has).
    explore : float
        While a residual common to the beads stays far above the noise, effects with
        evidence above this fraction of their threshold are tried too (module docstring).
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
    camera, names, candidates, bead_diameter = _checked(gain, offset, read_noise, folds,
                                                        effects, bead_diameter, r)
    ctx, beads, options, noise_source = _prepare(
        raw, img, r, beads, folds, camera, names, threshold=threshold, n_psf=n_psf,
        smoothing=smoothing, bead_diameter=bead_diameter, min_improvement=min_improvement,
        evident_improvement=evident_improvement, max_p=max_p, explore=explore,
        max_steps=max_steps, remove_motion=remove_motion)
    yield Progress("prepare", 0.05, f"{beads.summary()}; noise model: {noise_source}")
    run = partial(evaluate, psf_radius=r, folds=options["folds"])
    ctx, cf, an, held, steps, judge = yield from baseline_round(ctx, run, noise_source)
    if _baseline_only:
        return held
    ctx, cf, an, masked = yield from hot_pixel_round(ctx, cf, an, raw, img, judge, steps, run)
    first_cf, first_an = cf, an
    ctx, cf, an = yield from effect_rounds(
        ctx, cf, an, candidates, judge, steps, run, max_steps=max_steps, max_p=max_p,
        min_improvement=min_improvement, evident_improvement=evident_improvement,
        explore=explore)
    total, op = yield from final_round(ctx, cf, first_cf, judge, steps,
                                       bead_diameter=bead_diameter, remove_motion=remove_motion)
    options["saturation"] = saturation_record(raw, beads, r, None)
    return Diagnosis(steps=steps, **{k: total[k] for k in FIGURES}, operator=op, context=ctx,
                     analysis_before=first_an, analysis_after=an, crossfit_before=first_cf,
                     crossfit_after=cf, noise_source=noise_source, options=options,
                     masked_pixels=masked, heldout=held)


def _checked(gain, offset, read_noise, folds, effects, bead_diameter, r) -> tuple:
    """The camera's gain, offset and read noise (all or none measured), the effects'
    names and a fresh instance of each, the beads' diameter; ``folds`` checked."""
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
    return ((gain, offset, read_noise), names, [REGISTRY[n]() for n in names],
            check_bead_diameter(bead_diameter, r))


def _prepare(raw, img, r, beads, folds, camera, names, *, threshold, n_psf, smoothing,
             bead_diameter, **settings):
    """The context the loop starts from (the beads, detected or the user's table, their
    hot pixels masked, the noise model), the beads and the options as run: the folds
    (one bead at a time below ``2 folds`` beads) and ``settings`` in the record's order."""
    given = beads is not None
    beads = prepare_beads(raw, r, threshold=threshold, beads=beads)
    n_kept = int(np.count_nonzero(beads.kept))
    if n_kept < 2 * folds:  # few beads: each is judged by a model of all the others
        require_kept(beads, MIN_BEADS, reason="to judge each bead by a model learnt "
                     "without it (leave-one-bead-out)",
                     advice=GIVEN_ADVICE if given else DETECTION_ADVICE)
        folds = n_kept
    hot = spike_mask(img.shape, beads.hot_pixels)
    img = beads.clean_image(img)
    noise, noise_source = noise_model_with_source(raw, *camera, mask=hot)
    model = {k: v for k, v in (("n_psf", n_psf), ("smoothing", smoothing)) if v is not None}
    ctx = Context(image=img, pixel_mask=hot, beads=beads, noise=noise,
                  psf_radius=r, noise_from_image=camera[0] is None, estimate_kwargs=model,
                  bead_diameter=bead_diameter)
    options = {"folds": folds, "leave_one_bead_out": folds == n_kept,
               **{k: settings[k] for k in ("min_improvement", "evident_improvement", "max_p",
                                           "explore")},
               "n_psf": n_psf, "smoothing": smoothing, "max_steps": settings["max_steps"],
               "threshold": threshold, "psf_radius": r, "bead_diameter": bead_diameter,
               "remove_motion": settings["remove_motion"], "effects": names}
    return ctx, beads, options, noise_source


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
