"""What microscopists read off a 3D PSF, over the field: lateral and axial FWHM, the
focal shift (field curvature, a tilted focus), the astigmatic focal split and the
ellipticity.

:func:`psf_measures` measures one 3D PSF (Z, P, P):

* the **focal plane** ``z0``: the plane with the most light near the lateral centre
  (within one standard deviation of the narrowest plane), refined by a parabola through
  it and its neighbours (sub-plane);
* the **lateral FWHM** at ``z0`` along rows and columns, from the plane's second moments
  about its centroid within ``fit_radius`` (a Gaussian's ``2 sqrt(2 ln 2) sigma``), and
  their geometric mean;
* the **ellipticity** at ``z0``: ``1 - minor / major`` of the plane's moment ellipse;
* the **astigmatic focal split**: the planes (sub-plane) where the row width and the
  column width are smallest, ``z_col - z_row``;
* the **axial FWHM**: the width at half maximum of the axial profile (each plane's
  light within ``max(1.5, FWHM_lat / 2)`` pixels of the centre), linearly interpolated
  between planes.

Lengths are in planes and pixels; :func:`measure_table` converts them with the voxel
size. :func:`measure_maps` evaluates them on a grid of the field from an operator, and
:func:`bead_measures` on each bead's own patch (a direct fit, to check the smooth maps
against the beads).
"""

from __future__ import annotations

import numpy as np

#: Gaussian FWHM over sigma.
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))
#: The measures, in the order of the tables.
NAMES = ("focal_plane", "fwhm_lateral", "fwhm_row", "fwhm_col", "fwhm_axial",
         "ellipticity", "astigmatic_split")


def _moments(plane: np.ndarray, radius: float) -> tuple[float, float, float, float, float]:
    """Total, and the row, column and cross second moments of the non-negative part of
    a plane within ``radius`` of its centroid (one re-centring)."""
    p = plane.shape[-1]
    yy, xx = np.mgrid[:p, :p] - p // 2
    a = np.clip(plane, 0, None)
    cy = cx = 0.0
    for _ in range(2):
        m = ((yy - cy) ** 2 + (xx - cx) ** 2 <= radius ** 2) * a
        tot = m.sum()
        if tot <= 0:
            return 0.0, np.nan, np.nan, np.nan, np.nan
        cy, cx = float((m * yy).sum() / tot), float((m * xx).sum() / tot)
    dy, dx = yy - cy, xx - cx
    return (float(tot), float((m * dy * dy).sum() / tot), float((m * dx * dx).sum() / tot),
            float((m * dy * dx).sum() / tot), cy)


def _parabola_min(values: np.ndarray, k: int) -> float:
    """Sub-sample position of the extremum at ``k`` from a parabola through
    ``k - 1, k, k + 1`` (``k`` itself at an end)."""
    if 0 < k < len(values) - 1 and np.all(np.isfinite(values[k - 1:k + 2])):
        a, b, c = values[k - 1], values[k], values[k + 1]
        den = a - 2 * b + c
        if den != 0:
            return float(k + np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    return float(k)


def psf_measures(psf: np.ndarray, *, fit_radius: float | None = None) -> dict[str, float]:
    """The measures of one 3D PSF.

    Parameters
    ----------
    psf : ndarray of shape (Z, P, P)
        Background-free; plane ``z`` of the stack at index ``z``.
    fit_radius : float, optional
        Radius (pixels) of the moments; default ``P / 4``.

    Returns
    -------
    dict
        :data:`NAMES`: ``focal_plane`` (planes, sub-plane), ``fwhm_lateral``,
        ``fwhm_row``, ``fwhm_col`` (pixels), ``fwhm_axial`` (planes; NaN where the
        profile does not fall to half its maximum on both sides within the stack),
        ``ellipticity`` (0: round), ``astigmatic_split`` (planes, ``z_col - z_row``).
    """
    vol = np.asarray(psf, dtype=np.float64)
    z, p, _ = vol.shape
    radius = p / 4.0 if fit_radius is None else float(fit_radius)
    mom = np.array([_moments(vol[k], radius) for k in range(z)])  # (Z, 5)
    tot, syy, sxx, sxy = mom[:, 0], mom[:, 1], mom[:, 2], mom[:, 3]
    valid = (tot > 0.05 * np.nanmax(tot)) & np.isfinite(syy) & np.isfinite(sxx)
    width = np.where(valid, syy + sxx, np.inf)
    # the focal plane: the most light near the lateral centre (within one sd of the
    # narrowest plane), so that a PSF whose width does not change still has one
    yy, xx = np.mgrid[:p, :p] - p // 2
    dist = np.hypot(yy, xx)
    rc = max(1.5, float(np.sqrt(np.min(width) / 2)) if np.isfinite(np.min(width)) else 1.5)
    light = np.clip(vol[:, dist <= rc].sum(axis=1), 0, None)
    z0 = _parabola_min(-light, int(np.argmax(light)))
    wy = np.where(valid, syy, np.inf)
    wx = np.where(valid, sxx, np.inf)
    z_row = _parabola_min(np.where(valid, wy, np.nan), int(np.argmin(wy)))
    z_col = _parabola_min(np.where(valid, wx, np.nan), int(np.argmin(wx)))

    def at(values):  # linear interpolation at z0
        lo = int(np.clip(np.floor(z0), 0, z - 1))
        hi = min(lo + 1, z - 1)
        t = z0 - lo
        return (1 - t) * values[lo] + t * values[hi]

    s_y, s_x, s_xy = at(syy), at(sxx), at(sxy)
    tr, det = s_y + s_x, s_y * s_x - s_xy ** 2
    disc = np.sqrt(max(tr * tr / 4 - det, 0.0))
    major, minor = tr / 2 + disc, max(tr / 2 - disc, 0.0)
    fwhm_row = FWHM_PER_SIGMA * np.sqrt(max(s_y, 0.0))
    fwhm_col = FWHM_PER_SIGMA * np.sqrt(max(s_x, 0.0))
    fwhm_lat = float(np.sqrt(fwhm_row * fwhm_col))
    # axial profile: each plane's light near the lateral centre
    core = dist <= max(1.5, fwhm_lat / 2)
    prof = np.clip(vol[:, core].sum(axis=1), 0, None)
    fwhm_ax = _fwhm_1d(prof)
    return {"focal_plane": z0, "fwhm_lateral": fwhm_lat, "fwhm_row": float(fwhm_row),
            "fwhm_col": float(fwhm_col), "fwhm_axial": fwhm_ax,
            "ellipticity": float(1 - np.sqrt(minor / major)) if major > 0 else np.nan,
            "astigmatic_split": float(z_col - z_row)}


def _fwhm_1d(profile: np.ndarray) -> float:
    """Full width at half maximum of a 1-D profile (samples), linear between samples;
    NaN when it does not fall below half on both sides."""
    k = int(np.argmax(profile))
    half = profile[k] / 2
    if half <= 0:
        return np.nan
    left = np.flatnonzero(profile[:k] < half)
    right = np.flatnonzero(profile[k:] < half)
    if len(left) == 0 or len(right) == 0:
        return np.nan
    i, j = left[-1], k + right[0]
    zl = i + (half - profile[i]) / (profile[i + 1] - profile[i])
    zr = j - 1 + (profile[j - 1] - half) / (profile[j - 1] - profile[j])
    return float(zr - zl)


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
        Measure name -> ndarray (n_rows, n_cols), in planes and pixels.
    """
    _, h, w = operator.shape
    ys = (np.arange(n_rows) + 0.5) * h / n_rows - 0.5
    xs = (np.arange(n_cols) + 0.5) * w / n_cols - 0.5
    maps = {n: np.full((n_rows, n_cols), np.nan) for n in NAMES}
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            for name, v in psf_measures(operator.psf_at(y, x)).items():
                maps[name][i, j] = v
    return ys, xs, maps


def bead_measures(patches) -> dict[str, np.ndarray]:
    """The measures of each bead's own 3D patch (a direct fit, no model).

    Parameters
    ----------
    patches : Patches3D

    Returns
    -------
    dict
        Measure name -> ndarray (K,); ``focal_plane`` on the stack's planes.
    """
    out = {n: np.full(len(patches), np.nan) for n in NAMES}
    for k in range(len(patches)):
        for name, v in psf_measures(patches.psf[k]).items():
            out[name][k] = v
    out["focal_plane"] = out["focal_plane"] + patches.planes[0]
    return out


def map_uncertainty(operator, beads: dict[str, np.ndarray], centers: np.ndarray
                    ) -> dict[str, float]:
    """Each measure's uncertainty: the rms difference between the beads' direct fits and
    the model's PSF at the same positions (the scatter the smooth maps leave, noise and
    model error together). NaN where fewer than 3 beads have both."""
    model = {n: np.full(len(centers), np.nan) for n in NAMES}
    for k, (y, x) in enumerate(np.asarray(centers, float)):
        for name, v in psf_measures(operator.psf_at(y, x)).items():
            model[name][k] = v
    out = {}
    for n in NAMES:
        d = beads[n] - model[n]
        d = d[np.isfinite(d)]
        out[n] = float(np.sqrt(np.mean(d ** 2))) if len(d) >= 3 else np.nan
    return out


def measure_table(beads: dict[str, np.ndarray], centers: np.ndarray,
                  voxel_size: tuple[float, float, float] | None = None) -> list[dict]:
    """Rows of the per-bead table (for a CSV): position and every measure, with the
    lengths in µm too when the voxel size is known."""
    rows = []
    for k, (y, x) in enumerate(np.asarray(centers, float)):
        row = {"row_px": round(float(y), 3), "col_px": round(float(x), 3)}
        for n in NAMES:
            row[n] = None if not np.isfinite(beads[n][k]) else round(float(beads[n][k]), 4)
        if voxel_size is not None:
            dz, dy, _ = voxel_size
            for n, scale in (("fwhm_lateral", dy), ("fwhm_row", dy), ("fwhm_col", dy),
                             ("fwhm_axial", dz), ("astigmatic_split", dz)):
                v = row[n]
                row[f"{n}_um"] = None if v is None else round(v * scale, 4)
        rows.append(row)
    return rows


__all__ = ["NAMES", "bead_measures", "map_uncertainty", "measure_maps", "measure_table",
           "psf_measures"]
