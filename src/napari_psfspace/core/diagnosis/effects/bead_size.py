"""Beads of different sizes: each bead image is the PSF blurred by its own sphere.

A bead of diameter ``d`` is a uniform fluorescent sphere; its image is ``h * S(d)``, the
optical PSF ``h`` convolved with the sphere's projection (chord-length profile), whose
Fourier transform is ``T(d, k) = 3 (sin q - q cos q) / q^3`` with ``q = pi d |k|``. One
common size is absorbed by the model (it learns ``h * S(d)``); sizes that differ from
bead to bead are not. The effect brings every training patch to a common reference
diameter ``d_ref`` (``F^-1[F(patch_k) T(d_ref) / T(d_k)]``, regularised towards no
change where ``T(d_k)`` is small, :func:`change_size`), so the model learns
``h * S(d_ref)``, and fits each bead with the model times ``T(d_k) / T(d_ref)``. The
diameters follow the beads' brightness (``~ flux^(1/3)``, uniform dye density), scaled
so that the cross-fitted error is smallest. Everything is in pixels: the refined
operator of a diagnosis with this effect is the PSF seen through a bead of ``d_ref``
pixels (``params["bead_size"]["d_ref_px"]``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree

from ...beads.sphere import change_size
from ...common.progress import run_with_progress
from ..bead_tests import bead_flux
from ..crossfit import iter_crossfit
from ..residuals import BeadResiduals
from .base import Context, Effect


@dataclass(frozen=True)
class SizeFilter:
    """Per-bead size change, as the ``patch_filter`` / ``model_filter`` hooks call it.

    Attributes
    ----------
    positions : ndarray of shape (L, 2)
        Bead centres (row, column) in pixels.
    diameters : ndarray of shape (L,)
        Their diameters in pixels.
    d_ref : float
        Reference diameter (pixels) of the model.
    to_reference : bool
        True: bring images of the beads to ``d_ref`` (training patches); False: bring
        the model (at ``d_ref``) to each bead's diameter (fits).
    eps : float
        Regularisation (:func:`change_size`).
    tolerance : float
        A position farther than this (pixels) from every bead keeps ``d_ref``.
    """

    positions: np.ndarray
    diameters: np.ndarray
    d_ref: float
    to_reference: bool
    eps: float = 0.1
    tolerance: float = 2.0

    def diameters_at(self, positions) -> np.ndarray:
        """Diameter (pixels) of the bead nearest each position, shape (K,)."""
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        if len(self.positions) == 0 or len(pos) == 0:
            return np.full(len(pos), self.d_ref)
        dist, idx = cKDTree(self.positions).query(pos)
        return np.where(dist <= self.tolerance, self.diameters[idx], self.d_ref)

    def __call__(self, stack: np.ndarray, positions) -> np.ndarray:
        d = self.diameters_at(positions)
        if self.to_reference:
            return change_size(stack, d, self.d_ref, eps=self.eps)
        return change_size(stack, self.d_ref, d, eps=self.eps)


def _then(first, second):
    """``second(first(stack, positions), positions)``, or ``second`` alone."""
    if first is None:
        return second

    def both(stack, positions):
        return second(first(stack, positions), positions)

    return both


def _heldout(ctx: Context, folds: int, sizes: tuple | None = None
             ) -> tuple[np.ndarray, BeadResiduals]:
    """Cross-fitted residuals of every judged bead, in bead-table order.

    Parameters
    ----------
    ctx : Context
    folds : int
    sizes : (positions (K, 2), diameters (K,), d_ref), optional
        Bead sizes in pixels: the model is learnt from patches brought to ``d_ref`` and
        each bead is fitted with its own diameter.

    Returns
    -------
    bead_index : ndarray of shape (K,), sorted
    residuals : BeadResiduals
        In the order of ``bead_index``.
    """
    est_kw = dict(ctx.estimate_kwargs)
    fit_kw = {**ctx.fit_kwargs, "pixel_mask": ctx.pixel_mask}
    if sizes is not None and sizes[2] > 0:
        pos, diam, d_ref = sizes
        est_kw["patch_filter"] = _then(est_kw.get("patch_filter"),
                                       SizeFilter(pos, diam, d_ref, True))
        fit_kw["model_filter"] = _then(fit_kw.get("model_filter"),
                                       SizeFilter(pos, diam, d_ref, False))
    cf = run_with_progress(iter_crossfit(ctx.image, ctx.beads, ctx.noise,
                                         psf_radius=ctx.psf_radius, folds=folds,
                                         estimate_kwargs=est_kw, fit_kwargs=fit_kw))
    order = np.argsort(cf.bead_index)
    return cf.bead_index[order], cf.residuals.take(order)


def _in_table(res: BeadResiduals | None, table: np.ndarray
              ) -> tuple[np.ndarray, BeadResiduals] | None:
    """``(bead_index, residuals)`` in bead-table order when every residual's position is
    one of ``table`` (L, 2) (the diagnosis's own cross-fit), else None."""
    if res is None or len(res) == 0:
        return None
    where = {tuple(p): i for i, p in enumerate(np.asarray(table, dtype=np.float64))}
    index = np.array([where.get(tuple(p), -1) for p in res.positions])
    if (index < 0).any() or len(np.unique(index)) != len(index):
        return None
    order = np.argsort(index)
    return index[order], res.take(order)


class BeadSize(Effect):
    """Beads of different diameters (the bigger ones brighter): each bead is fitted with
    the model PSF blurred by its own sphere, and the model is learnt from patches brought
    to one reference diameter.

    Diameters follow the brightness (uniform dye density: flux ``~ d^3``),
    ``d_k = d_ref (F_k / median F)^(1/3)`` with ``F`` the model-free patch flux
    (:func:`~napari_psfspace.core.diagnosis.analysis.bead_flux`); the scale ``d_ref`` (pixels, the
    diameter of the median bead, the model's reference) minimises the cross-fitted
    error (``folds`` folds) of the beads the current model fits informatively: a grid of
    ``n_grid`` steps up to ``max_fraction * psf_radius`` (extended while the error still
    drops at its end), then half a step on either side of the best. When the beads'
    nominal diameter is known (``bead_diameter``), it is the median bead's: only that
    scale is tried.
    """

    name = "bead_size"
    description = ("beads of different sizes (each bead's image is the PSF blurred by its "
                   "own sphere; diameters from the brightness, ~ flux^(1/3))")
    tests = ("bead_width",)
    n_grid: ClassVar[int] = 6
    max_fraction: ClassVar[float] = 0.5
    folds: ClassVar[int] = 5

    def fit(self, ctx: Context, analysis) -> dict:
        found = _in_table(getattr(analysis, "residuals", None), ctx.beads.positions)
        index, res = found if found is not None else _heldout(ctx, self.folds)
        pos = ctx.beads.positions[index]
        flux = bead_flux(ctx.image, pos, ctx.psf_radius)
        judge = res.informative
        good = judge & (flux > 0)
        empty = {"d_ref_px": 0.0, "units": "pixels", "positions": [], "diameters_px": []}
        if good.sum() < 5:
            return empty
        rel = np.minimum(np.cbrt(np.clip(flux, 0.0, None) / np.median(flux[good])), 3.0)
        step = self.max_fraction * float(ctx.psf_radius) / self.n_grid
        grid = [0.0]
        cost = [float(np.mean(res.rel_energy[judge]))]

        def evaluate(d: float) -> None:
            grid.append(d)
            _, r = _heldout(ctx, self.folds, (pos, d * rel, d))
            cost.append(float(np.mean(r.rel_energy[judge])))

        if ctx.bead_diameter > 0:  # the median bead has the nominal diameter
            evaluate(float(ctx.bead_diameter))
        else:
            for d in step * np.arange(1, self.n_grid + 1):
                evaluate(float(d))
            # the best at the end of the grid: go on while the error drops (up to 2 r)
            while np.argmin(cost) == len(cost) - 1 and grid[-1] + step <= 2 * ctx.psf_radius:
                evaluate(grid[-1] + step)
            best = grid[int(np.argmin(cost))]
            for d in (best - step / 2, best + step / 2):
                if d > 0:
                    evaluate(float(d))
        best = grid[int(np.argmin(cost))]
        search = {"d_ref_px": np.round(grid, 3).tolist(),
                  "heldout_error": np.round(cost, 5).tolist(), "folds": self.folds}
        if best == 0:
            return {**empty, "search": search}
        diam = best * rel
        return {"d_ref_px": round(best, 4), "units": "pixels",
                "diameter_px_percentiles": {str(q): round(float(np.percentile(diam[good], q)),
                                                          3) for q in (5, 50, 95)},
                "search": search,
                "positions": np.round(pos, 3).tolist(),
                "diameters_px": np.round(diam, 4).tolist()}

    def apply(self, ctx: Context, params: dict) -> Context:
        d_ref = float(params["d_ref_px"])
        pos = np.asarray(params["positions"], dtype=np.float64).reshape(-1, 2)
        diam = np.asarray(params["diameters_px"], dtype=np.float64).reshape(-1)
        est = dict(ctx.estimate_kwargs)
        fit = dict(ctx.fit_kwargs)
        if d_ref > 0 and len(pos):
            est["patch_filter"] = _then(est.get("patch_filter"),
                                        SizeFilter(pos, diam, d_ref, True))
            fit["model_filter"] = _then(fit.get("model_filter"),
                                        SizeFilter(pos, diam, d_ref, False))
        return ctx.with_effect(self.name, params, estimate_kwargs=est, fit_kwargs=fit)
