"""What microscopists read off a 3D PSF, over the field: the measures of
:mod:`napari_psfspace.core.common.measures` (a Gaussian with an offset fitted in focus and
along the axis, as napari-psf-analysis quotes them; the focal plane from the peak; the
astigmatic split from the two line foci) on a grid of the field (:func:`measure_maps`),
on each bead's own patch (:func:`bead_measures`, a direct fit with no model;
:func:`direct_bead_measures` on its pixels as they were recorded) and in a
table with the units (:func:`measure_table`, nm where the voxel size is known).
"""

from __future__ import annotations

import numpy as np

from ..common.measures import NAMES, UNITS_PX, in_units, psf_measures

#: The measures of the maps and tables: :data:`NAMES` and how large an astigmatic split
#: the planes about focus could show.
MEASURES = (*NAMES, "astigmatic_split_limit")


def _measure_into(out: dict[str, np.ndarray], index, psf) -> None:
    m = psf_measures(psf)
    for name in MEASURES:
        out[name][index] = m[name]


def measure_maps(operator, n_rows: int = 8, n_cols: int = 8
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The measures of an operator's PSFs on a grid of the field.

    Parameters
    ----------
    operator : ProductConvolution3D
    n_rows, n_cols : int
        Grid size (the centres of an ``n_rows x n_cols`` tiling).

    Returns
    -------
    ys, xs : ndarray of shape (n_rows,), (n_cols,)
        Grid positions, pixels.
    maps : dict
        Measure name (:data:`MEASURES`) -> ndarray (n_rows, n_cols), in planes and
        pixels (:data:`~napari_psfspace.core.common.measures.UNITS_PX`);
        ``focal_plane`` on the stack's planes.
    """
    _, h, w = operator.image_shape
    ys = (np.arange(n_rows) + 0.5) * h / n_rows - 0.5
    xs = (np.arange(n_cols) + 0.5) * w / n_cols - 0.5
    maps = {n: np.full((n_rows, n_cols), np.nan) for n in MEASURES}
    if operator.n_psf == 1:  # one kernel, scaled: every measure is the same everywhere
        _measure_into(maps, (slice(None), slice(None)), operator.psf_at(ys[0], xs[0]))
        return ys, xs, maps
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            _measure_into(maps, (i, j), operator.psf_at(y, x))  # on the stack's planes
    return ys, xs, maps


def bead_measures(patches) -> dict[str, np.ndarray]:
    """The measures of each bead's own 3D patch (a direct fit, no model).

    Parameters
    ----------
    patches : Patches3D

    Returns
    -------
    dict
        Measure name (:data:`MEASURES`) -> ndarray (K,); ``focal_plane`` on the stack's
        planes.
    """
    out = {n: np.full(len(patches), np.nan) for n in MEASURES}
    for k in range(len(patches)):
        _measure_into(out, k, patches.psf[k])
    out["focal_plane"] = out["focal_plane"] + patches.planes[0]
    return out


def direct_bead_measures(stack, estimation) -> dict[str, np.ndarray]:
    """The measures of each bead in a model (``estimation.basis.inliers``), fitted to its
    own pixels: its patch cut at the nearest whole pixel and plane, not re-sampled to its
    sub-pixel centre nor moved in z (the Gaussian fits find the centre). Re-sampling
    widens a PSF sampled near or below Nyquist (a lateral FWHM of one or two pixels);
    these are the widths a microscopist's own fit of the bead reads.

    Parameters
    ----------
    stack : array_like of shape (Z, H, W)
        The stack the model was learnt from.
    estimation : Estimation3D

    Returns
    -------
    dict
        Measure name (:data:`MEASURES`) -> ndarray (K,) in the order of
        ``estimation.patches.centers[estimation.basis.inliers]``; ``focal_plane`` on the
        stack's planes.
    """
    from .patches3d import extract_patches_3d

    p = estimation.patches.subset(estimation.basis.inliers)
    half = (len(p.planes) - 1) // 2
    raw = extract_patches_3d(np.asarray(stack, np.float32), np.round(p.centers), p.r,
                             plane=int(p.planes[half]), z_radius=half)
    return bead_measures(raw)


def model_measures(operator, centers: np.ndarray) -> dict[str, np.ndarray]:
    """The measures of the model's PSF at each position ``(row, column)``, shape (K, 2):
    measure name -> ndarray (K,), ``focal_plane`` on the stack's planes."""
    centers = np.asarray(centers, float).reshape(-1, 2)
    out = {n: np.full(len(centers), np.nan) for n in MEASURES}
    for k, (y, x) in enumerate(centers):
        _measure_into(out, k, operator.psf_at(y, x))
    return out


def map_uncertainty(operator, beads: dict[str, np.ndarray], centers: np.ndarray
                    ) -> dict[str, float]:
    """Each measure's uncertainty: the rms difference between the beads' direct fits and
    the model's PSF at the same positions (the scatter the smooth maps leave, noise and
    model error together). NaN where fewer than 3 beads have both."""
    model = model_measures(operator, centers)
    out = {}
    for n in NAMES:
        d = beads[n] - model[n]
        d = d[np.isfinite(d)]
        out[n] = float(np.sqrt(np.mean(d ** 2))) if len(d) >= 3 else np.nan
    return out


def measure_table(beads: dict[str, np.ndarray], centers: np.ndarray,
                  voxel_size: tuple[float, float, float] | None = None) -> list[dict]:
    """Rows of the per-bead table (for a CSV): position and every measure, each column
    named with its unit (``_px``, ``_planes``), and in nm too (``_nm``) when the voxel
    size ``(dz, dy, dx)`` (µm) is known."""
    rows = []
    for k, (y, x) in enumerate(np.asarray(centers, float)):
        row = {"row_px": round(float(y), 3), "col_px": round(float(x), 3)}
        values = {n: float(beads[n][k]) for n in MEASURES}
        for n in MEASURES:
            unit = UNITS_PX[n]
            key = f"{n}_{unit}" if unit else n
            row[key] = round(values[n], 4) if np.isfinite(values[n]) else None
        if voxel_size is not None:
            nm, units = in_units(values, voxel_size)
            for n in MEASURES:
                if units[n] == "nm":
                    row[f"{n}_nm"] = round(nm[n], 1) if np.isfinite(nm[n]) else None
        rows.append(row)
    return rows


__all__ = ["MEASURES", "NAMES", "bead_measures", "direct_bead_measures", "map_uncertainty",
           "measure_maps",
           "measure_table", "model_measures", "psf_measures"]
