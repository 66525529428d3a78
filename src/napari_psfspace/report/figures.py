"""The report's figures as arrays: each bead's held-out excess error on a coarse map of
the field, the mean residual patch, the worst beads' residuals, and their colours
(numpy alone; the *Diagnose* dock widget shows the same maps as layers).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..core.common.mosaic import mosaic
from ..core.diagnosis.residuals import BeadResiduals

#: Figure files written by :func:`write_report`, with what each shows.
FIGURES = {
    "residual_map_before.png": "held-out excess error of each bead over the field, "
                               "plain model",
    "residual_map_after.png": "held-out excess error of each bead over the field, "
                              "final model",
    "mean_residual_before.png": "mean normalised residual patch over the beads, plain model",
    "mean_residual_after.png": "mean normalised residual patch over the beads, final model",
    "residual_patches_before.png": "normalised residual patches of the 16 worst beads, "
                                   "plain model",
    "residual_patches_after.png": "normalised residual patches of the 16 worst beads, "
                                  "final model",
}

#: Largest |normalised residual| (noise sd) shown in the patch mosaics.
PATCH_LIMIT = 5.0

# ------------------------------------------------------------------ maps (numpy only)
def excess_error(res: BeadResiduals) -> np.ndarray:
    """Each bead's relative residual energy minus what noise alone leaves, shape (K,)."""
    return np.asarray(res.rel_energy, float) - np.asarray(res.floor, float)

def map_cell_size(shape: tuple[int, int], cells: int = 64) -> float:
    """Pixels per cell of a :func:`residual_map` of an image of this shape."""
    return max(shape) / float(cells)

def residual_map(positions, values, shape: tuple[int, int], *, cells: int = 64,
                 radius: float | None = None) -> np.ndarray:
    """A coarse map of the field where each bead paints a disk of its value.

    Parameters
    ----------
    positions : array_like of shape (K, 2)
        Bead centres (row, column) in pixels of the image.
    values : array_like of shape (K,)
        One value per bead (non-finite ones are left out).
    shape : tuple of int
        ``(M, N)`` of the image.
    cells : int
        Cells along the longer side of the image (square cells of
        :func:`map_cell_size` pixels).
    radius : float, optional
        Disk radius in cells; default ``0.35`` of the mean spacing of the beads, between
        1 and 6 cells.

    Returns
    -------
    ndarray of shape (ceil(M / c), ceil(N / c)), float64
        NaN where no bead paints; where disks overlap the larger value shows.
    """
    pos = np.asarray(positions, float).reshape(-1, 2)
    val = np.asarray(values, float).reshape(-1)
    if len(pos) != len(val):
        raise ValueError(f"{len(pos)} positions but {len(val)} values.")
    cell = map_cell_size(shape, cells)
    gh, gw = math.ceil(shape[0] / cell), math.ceil(shape[1] / cell)
    out = np.full((gh, gw), np.nan)
    ok = np.isfinite(val) & np.all(np.isfinite(pos), axis=1)
    pos, val = pos[ok], val[ok]
    if not len(val):
        return out
    if radius is None:
        radius = float(np.clip(0.35 * np.sqrt(gh * gw / len(val)), 1.0, 6.0))
    yy, xx = np.mgrid[0:gh, 0:gw] + 0.5
    for k in np.argsort(val, kind="stable"):  # largest painted last: on top
        cy, cx = (pos[k] + 0.5) / cell
        out[(yy - cy) ** 2 + (xx - cx) ** 2 <= radius**2] = val[k]
    return out

def mean_residual_patch(res: BeadResiduals) -> np.ndarray:
    """Mean normalised residual patch over the beads (pixels in each bead's fit), (P, P).

    Pixels no bead fitted are 0.
    """
    if len(res) == 0:
        return np.zeros(res.data.shape[1:])
    nres = np.where(res.fit_mask, res.normalised_residual, 0.0)
    count = res.fit_mask.sum(axis=0)
    return nres.sum(axis=0) / np.maximum(count, 1)

def worst_residual_patches(res: BeadResiduals, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Normalised residual patches of the ``n`` beads of largest excess error.

    Returns
    -------
    patches : ndarray of shape (min(n, K), P, P)
        Worst first; 0 outside each bead's fit.
    index : ndarray of shape (min(n, K),)
        Their entries in ``res``.
    """
    order = np.argsort(-np.nan_to_num(excess_error(res), nan=-np.inf), kind="stable")[:n]
    return np.where(res.fit_mask[order], res.normalised_residual[order], 0.0), order

def map_limit(*maps: np.ndarray, percentile: float = 98.0) -> float:
    """A common upper colour limit for residual maps: a high percentile of their values."""
    vals = np.concatenate([np.ravel(m) for m in maps]) if maps else np.zeros(0)
    vals = vals[np.isfinite(vals)]
    hi = float(np.percentile(vals, percentile)) if len(vals) else 0.0
    return hi if hi > 0 else 1.0

def colorize(values: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """Viridis RGB image of a 2-D array (NaN: dark grey), uint8 (M, N, 3)
    (:func:`~napari_psfspace.figure.apply_colormap`)."""
    from ..figure import apply_colormap

    return apply_colormap(values, vmin, vmax, "viridis")

def diverging_grey(values: np.ndarray, limit: float) -> np.ndarray:
    """Grey ramp: ``-limit`` black, 0 mid-grey, ``+limit`` white (clipped), uint8."""
    v = np.nan_to_num(np.asarray(values, float))
    t = np.clip(v / (limit if limit > 0 else 1.0), -1.0, 1.0)
    return np.round(127.5 + 127.5 * t).astype(np.uint8)

def figure_arrays(diagnosis, *, cells: int = 64, n_patches: int = 16) -> dict[str, Any]:
    """The figures of a diagnosis as arrays, before and after on common scales.

    Parameters
    ----------
    diagnosis : Diagnosis
    cells : int
        Cells along the longer side of the residual maps.
    n_patches : int
        Worst beads shown in the patch mosaics.

    Returns
    -------
    dict
        ``map_before``, ``map_after`` (float maps, NaN without a bead), ``map_limit``,
        ``cell_size`` (pixels per cell), ``mean_before``, ``mean_after`` (P, P),
        ``mean_limit``, ``patches_before``, ``patches_after`` (mosaics of normalised
        residuals).
    """
    shape = diagnosis.context.image.shape
    out: dict[str, Any] = {"cell_size": map_cell_size(shape, cells)}
    for when, cf in (("before", diagnosis.crossfit_before), ("after", diagnosis.crossfit_after)):
        res = cf.residuals
        out[f"map_{when}"] = residual_map(res.positions, excess_error(res), shape, cells=cells)
        out[f"mean_{when}"] = mean_residual_patch(res)
        tiles, _ = worst_residual_patches(res, n_patches)
        out[f"patches_{when}"] = (mosaic(tiles, gap=1, normalize="none") if len(tiles)
                                  else np.zeros((1, 1)))
    out["map_limit"] = map_limit(out["map_before"], out["map_after"])
    out["mean_limit"] = float(max(np.abs(out["mean_before"]).max(),
                                  np.abs(out["mean_after"]).max())) or 1.0
    return out


__all__ = ["colorize", "diverging_grey", "excess_error", "figure_arrays", "FIGURES",
           "map_cell_size", "map_limit", "mean_residual_patch", "PATCH_LIMIT",
           "residual_map", "worst_residual_patches"]
