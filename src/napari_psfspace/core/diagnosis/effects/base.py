"""The common small interface of the model extensions ("effects") that diagnose adds.

An :class:`Effect` reads the residual :class:`~napari_psfspace.core.diagnosis.analysis.Analysis`
(``evidence``), fits its parameters from the image and the residuals (``fit``), and
returns a new model :class:`Context` with itself applied (``apply``). The diagnosis loop
keeps an effect only if the cross-fitted held-out error drops significantly.

Subclasses register themselves by their ``name`` (PIFF's pattern): a name collision is an
error.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np

from ...beads.detect import Beads
from ...beads.noise import NoiseModel
from ..analysis import Analysis

REGISTRY: dict[str, type[Effect]] = {}


@dataclass(frozen=True)
class Context:
    """Everything that defines the model being diagnosed.

    Attributes
    ----------
    image : ndarray of shape (M, N), float64
        The image in ADU, corrected by the effects applied so far (e.g. fixed-pattern
        offsets removed, outlier pixels inpainted).
    pixel_mask : ndarray of shape (M, N), bool
        Pixels the bead fits ignore (outliers, saturated pixels).
    beads : Beads
        Beads with sub-pixel positions; "kept" ones are fitted and cross-validated.
    noise : NoiseModel
    psf_radius : float
    estimate_kwargs : dict
        Options of :func:`~napari_psfspace.core.model.estimate.iter_estimate`.
    fit_kwargs : dict
        Options of :func:`~napari_psfspace.core.diagnosis.residuals.fit_beads` (e.g. companions).
    applied : tuple of str
        Names of the effects applied, in order.
    params : dict
        Fitted parameters of each applied effect (JSON-ready).
    noise_from_image : bool
        The noise model was estimated from the image (not given by the user).
    throughput_degree : int
        Degree of the log-polynomial throughput over the field
        (:mod:`~napari_psfspace.core.diagnosis.photometry`; 0: uniform, the plain model).
    bead_diameter : float
        The beads' nominal diameter in pixels, when the user gave it (0: unknown). The
        models are learnt and judged on bead images; only the final operator has the
        sphere divided out.
    """

    image: np.ndarray
    pixel_mask: np.ndarray
    beads: Beads
    noise: NoiseModel
    psf_radius: float
    estimate_kwargs: dict = field(default_factory=dict)
    fit_kwargs: dict = field(default_factory=dict)
    applied: tuple[str, ...] = ()
    params: dict = field(default_factory=dict)
    noise_from_image: bool = True
    throughput_degree: int = 0
    bead_diameter: float = 0.0

    def renoised(self, image: np.ndarray) -> NoiseModel:
        """The noise model for a corrected image: re-estimated when it came from the
        image (photon transfer sees uncorrected camera patterns as noise), else kept."""
        if not self.noise_from_image:
            return self.noise
        from ...beads.noise import NoiseModelError, estimate_noise

        if self.noise.kind != "photon transfer":  # a fallback stays the same fallback
            return self.noise
        try:
            return estimate_noise(image, mask=self.pixel_mask, offset=self.noise.offset)
        except NoiseModelError:
            return self.noise

    def with_effect(self, name: str, params: dict, **changes: Any) -> Context:
        """A copy with ``changes`` and the effect recorded."""
        return replace(self, applied=(*self.applied, name),
                       params={**self.params, name: params}, **changes)


class Effect:
    """Base class: one thing the model may lack.

    Class attributes
    ----------------
    name : str
        Registry key (also in reports).
    description : str
        One line for reports: what it is, in a microscopist's words.
    tests : tuple of str
        Names of the analysis tests that are evidence for it.
    own_evidence : bool
        See the attribute's comment.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    tests: ClassVar[tuple[str, ...]] = ()
    #: The effect has a test of its own that reads its correction: it may be kept when
    #: that test goes from significant to not while the held-out error is not worse
    #: (a physical effect of few parameters whose correction no held-out error need
    #: show: a compressive response goes into the learnt PSF, a camera pattern sits
    #: in the background). Not the bead size: its bead-width test is the compressive
    #: response's too (bright beads look wider either way), and on its own test it took
    #: the response's place.
    own_evidence: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.name:
            if cls.name in REGISTRY:
                raise ValueError(f"effect name {cls.name!r} registered twice")
            REGISTRY[cls.name] = cls

    def evidence(self, analysis: Analysis) -> float:
        """Strongest evidence among this effect's tests (> 1: significant)."""
        return max((analysis.tests[t].evidence for t in self.tests if t in analysis.tests),
                   default=0.0)

    def applicable(self, ctx: Context) -> bool:
        """False when the effect is already in the model (or cannot be applied again)."""
        return self.name not in ctx.applied

    def fit(self, ctx: Context, analysis: Analysis) -> dict:
        """Estimate the effect's parameters (JSON-ready)."""
        raise NotImplementedError

    def apply(self, ctx: Context, params: dict) -> Context:
        """The model context with the effect included."""
        raise NotImplementedError

    def reading_after(self, test: str, after: Analysis, ctx: Context, cf) -> float | None:
        """The own test ``test`` read on the model with the effect (context ``ctx``, its
        cross-fit ``cf``): by default the analysis's, which the model's residuals make.
        An effect the residual analysis does not see (a throughput fitted to the beads'
        amplitudes) reads it on held-out values instead. None: not read."""
        t = after.tests.get(test)
        return None if t is None else t.strength
