"""Nonlinear detector response: bright pixels are compressed (or expanded).

The response above the camera offset is modelled as ``y = x (1 - c x / x_ref)`` (ADU),
``x_ref`` the brightest pixel above the offset, ``c > 0`` compressive (pile-up, dead
time, a camera near full well), ``c < 0`` expansive (inverted too, but not fitted: see
:data:`C_GRID`). Bright beads then look flatter
than faint ones: the PSF model, an average, is too sharp for the bright beads and too
flat for the faint ones, which the ``core_vs_amplitude`` test sees. The effect fits ``c``
so that this dependence vanishes and linearises the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...beads.window import radial_distance
from ..bead_tests import core_residuals, core_trend, round_beads
from .base import Context, Effect

#: Candidate response coefficients ``c`` (``c < 1/4`` keeps the response increasing up to
#: ``x_ref``): compressive ones only. A detector compresses (pile-up, dead time, full
#: well); the one expansive fit the power bench made was on a vignetted scene with no
#: response at all. The sign of the trend
#: does not tell the two apart: a compressive response reads z -9 on an aberration-free
#: field and +5 to +10 on the family's aberrated ones.
C_GRID = np.round(np.arange(0.0, 0.2451, 0.02), 4)


def linearise(values, c: float, x_ref: float, offset: float) -> np.ndarray:
    """Invert ``y = x (1 - c x / x_ref)`` (values in ADU including ``offset``).

    Values beyond the response's turning point (``c > 0``) are held at it.
    """
    y = np.asarray(values, dtype=np.float64) - offset
    if c == 0:
        return y + offset
    disc = np.maximum(1.0 - 4.0 * c * y / x_ref, 0.0)
    x = (1.0 - np.sqrt(disc)) * x_ref / (2.0 * c)
    return x + offset


@dataclass(frozen=True)
class Response:
    """The detector response ``y = x (1 - c x / x_ref)`` above ``offset`` (ADU)."""

    c: float
    x_ref: float
    offset: float

    def forward(self, values) -> np.ndarray:
        """Recorded ADU of linear values (ADU, offset included)."""
        x = np.asarray(values, dtype=np.float64) - self.offset
        if self.c > 0:  # held at the turning point
            x = np.minimum(x, self.x_ref / (2 * self.c))
        return x * (1.0 - self.c * x / self.x_ref) + self.offset

    def slope(self, values) -> np.ndarray:
        """``dy / dx`` at linear values."""
        x = np.asarray(values, dtype=np.float64) - self.offset
        return 1.0 - 2.0 * self.c * x / self.x_ref

    def inverse(self, values) -> np.ndarray:
        """Linear values of recorded ADU."""
        return linearise(values, self.c, self.x_ref, self.offset)


def _core_trend(res, c: float, x_ref: float, offset: float, core: np.ndarray) -> float:
    """Spearman z of the beads' core residual (relative to the amplitude) against
    amplitude after linearising their pixels with ``c`` and refitting amplitude and
    background to the model's shapes (the ``core_vs_amplitude`` test's statistic)."""
    amp, cores = core_residuals(res, core, linearise(res.data, c, x_ref, offset))
    return core_trend(amp, cores, res.positions)[1]


def _dark_level(ctx: Context) -> float:
    """The camera offset (ADU): given, else where the noise model's variance would vanish
    (``-b / a``, read noise neglected), at most the darkest unmasked pixel."""
    low = float(np.min(ctx.image[~ctx.pixel_mask]))
    if ctx.noise.offset is not None:
        return float(ctx.noise.offset)
    if ctx.noise.gain > 0:
        return min(-ctx.noise.intercept / ctx.noise.gain, low)
    return low


class Nonlinearity(Effect):
    """Linearise a quadratic detector response fitted from the beads."""

    name = "nonlinearity"
    description = ("nonlinear detector response (bright pixels compressed; the image is "
                   "linearised)")
    tests = ("core_vs_amplitude",)
    own_evidence = True

    def fit(self, ctx: Context, analysis) -> dict:
        res = analysis.residuals
        offset = _dark_level(ctx)
        x_ref = float(np.max(ctx.image[~ctx.pixel_mask]) - offset)
        p = res.data.shape[-1]
        core = radial_distance(p) <= max(1.5, ctx.psf_radius / 4)
        # on the round beads, as the test reads it (a merged companion flattens its bead's
        # core as it brightens it)
        use = res.informative & round_beads(res, psf_radius=ctx.psf_radius)
        sub = res.take(use)
        z = np.array([_core_trend(sub, c, x_ref, offset, core) for c in C_GRID])
        # the zero crossing of the trend (interpolated), else the smallest |z|
        best = float(C_GRID[int(np.argmin(np.abs(z)))])
        sign = np.sign(z)
        cross = np.flatnonzero(sign[:-1] * sign[1:] < 0)
        if len(cross):
            i = cross[int(np.argmin(np.abs(C_GRID[cross] - best)))]
            best = float(C_GRID[i] - z[i] * (C_GRID[i + 1] - C_GRID[i]) / (z[i + 1] - z[i]))
        elif best in (C_GRID[0], C_GRID[-1]):
            # the trend does not vanish inside the grid: no quadratic response describes
            # it (a fit that runs to the grid's edge describes something else)
            raise ValueError(
                f"no detector response y = x (1 - c x / x_ref) with c in [{C_GRID[0]:g}, "
                f"{C_GRID[-1]:g}] removes the core-vs-brightness trend (|z| >= "
                f"{np.abs(z).min():.1f} throughout): not a quadratic response")
        return {"c": round(best, 4), "x_ref_adu": x_ref, "offset_adu": offset,
                "trend_z_by_c": np.column_stack([C_GRID, z.round(2)]).tolist()}

    def apply(self, ctx: Context, params: dict) -> Context:
        # the PSF is learnt on the linearised image; the beads are judged on the recorded
        # pixels under the recorded image's noise model (fit_beads' ``response``)
        response = Response(params["c"], params["x_ref_adu"], params["offset_adu"])
        image = response.inverse(ctx.image)
        return ctx.with_effect(self.name, params, image=image,
                               fit_kwargs={**ctx.fit_kwargs, "response": response})
