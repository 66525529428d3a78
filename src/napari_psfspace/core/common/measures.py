"""What a microscopist reads off a PSF: FWHM, focus, astigmatism, ellipticity.

One module for every place a width is quoted: the 3D maps and the per-bead table of a
z-stack, the 2-D model's summary and the reports. The widths are those of a **Gaussian
with a constant offset fitted by least squares** (:mod:`.gaussfit`), as
napari-psf-analysis and PSF-Extractor quote them, so that the numbers agree with the
tools microscopists already use:

* **lateral FWHM** on the plane in focus: a 2-D Gaussian with a full covariance fitted
  to the whole plane, then refitted within :data:`CORE` FWHMs of its centre (a
  Gaussian fitted over the rings too reads an Airy disk 4-6 % narrow; on the core it
  reads it within 2 %: ``bench/bench_fwhm_reference.py``); its widths along the rows
  (``fwhm_row``, the y axis), the columns (``fwhm_col``, x) and the ellipse's principal
  axes (``fwhm_major``, ``fwhm_minor``);
  ``fwhm_lateral`` is the geometric mean of the principal widths;
* **ellipticity** ``1 - fwhm_minor / fwhm_major`` (0: round);
* **focal plane** (3D): the plane of the highest peak near the lateral centre, refined
  by a parabola through its neighbours (sub-plane). High-NA rings out of focus spread
  their light; the peak is where it concentrates;
* **axial FWHM** (3D): a 1-D Gaussian with an offset (refitted on its core likewise)
  fitted to the profile through the
  lateral centre (each plane sampled, bilinearly, at the centre fitted in focus). Where
  the stack does not reach a FWHM beyond the centre on both sides, a shorter profile
  cannot tell the offset from the width: the offset is held at 0 (the PSF is
  background-free), and the FWHM is NaN unless its half-maximum points lie in the stack;
* **astigmatic split** (3D): the two line foci. Each plane whose peak keeps at least
  :data:`MIN_PEAK_SHARE` of the focal peak (the contiguous run about focus) gets its own
  2-D fit. Each axis' line focus is the minimum of its width **nearest the focal plane**
  (a descent from focus over the widths smoothed across 3 planes), refined by a parabola
  through the squared widths within :data:`LINE_FOCUS_REACH` planes of it (the
  Gaussian-beam law ``w^2 = w0^2 (1 + ((z - c) / d)^2)`` about its waist). The split is
  ``z_col - z_row`` (planes). One parabola over every plane fitted reads a split short
  (the widths rise unevenly about each line focus; the pyotf oracle in
  ``bench/bench_fwhm_reference.py --sets astigmatism``), and the widths beyond the line
  foci can dip again where a 2-D fit catches a side lobe: hence the nearest minimum. A
  line focus at the end of the planes fitted is beyond what the stack shows: the split
  is then NaN, and ``astigmatic_split_limit`` (the extent of the planes fitted) says how
  large a split the stack could have shown.

Lengths are in pixels and planes; :func:`in_units` turns them into nm with the voxel
size, and :func:`diffraction_limit` gives the widefield limits for the ratio.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from .gaussfit import FWHM_PER_SIGMA, fit_gaussian_1d, fit_gaussian_2d

#: The Gaussian is refitted within this many FWHMs of its centre (0: no refit).
CORE = 1.3
#: The planes fitted for the line foci keep at least this share of the focal peak.
MIN_PEAK_SHARE = 0.3
#: Planes either side of a line focus through which its parabola is fitted (fewer scatter
#: more against the pyotf oracle: ``bench/bench_fwhm_reference.py --sets astigmatism``).
LINE_FOCUS_REACH = 3
#: A 2-D PSF is quoted a Gaussian FWHM only while it is a spot: while its central lobe
#: (out to the first minimum of its azimuthal profile about the fitted centre) holds at
#: least this share of its energy above the background. Set between the shares of the
#: spots and of the rings, crosses and defocused disks of three optics codes
#: (``bench/bench_spot_shape.py``).
SPOT_CORE = 0.33
#: The lateral measures, in the order of the tables (pixels, but ``ellipticity``).
LATERAL = ("fwhm_lateral", "fwhm_row", "fwhm_col", "fwhm_major", "fwhm_minor", "ellipticity")
#: The measures of a 3D PSF, in the order of the tables.
NAMES = ("focal_plane", *LATERAL, "fwhm_axial", "astigmatic_split")
#: The unit of each measure without a voxel size, and with one.
UNITS_PX = {"focal_plane": "planes", "fwhm_axial": "planes", "astigmatic_split": "planes",
            "ellipticity": "", "astigmatic_split_limit": "planes",
            **{n: "px" for n in LATERAL if n != "ellipticity"}}


def lateral_measures(plane, *, centre: tuple[float, float] | None = None,
                     radius: float | None = None) -> dict[str, float]:
    """The lateral measures of one PSF plane (pixels).

    Parameters
    ----------
    plane : array_like of shape (P, Q)
        A background-free PSF plane or a bead's patch (an offset is fitted).
    centre, radius : optional
        Fit only the disk of ``radius`` pixels about ``centre`` (row, column).

    Returns
    -------
    dict
        :data:`LATERAL`, ``angle`` (the major axis from the rows towards the columns,
        radians), ``cov_rr``, ``cov_rc``, ``cov_cc`` (the fitted covariance, pixels^2)
        and ``centre_row``, ``centre_col`` (pixels in the plane); NaN where the fit
        failed.
    """
    g = fit_gaussian_2d(plane, centre=centre, radius=radius)
    if g.ok and CORE:  # refit on the core: the rings and wings bias a Gaussian narrow
        major = g.principal[0]
        g = fit_gaussian_2d(plane, centre=g.centre, radius=max(CORE * major, 2.5))
    return {**_from_covariance(g.covariance if g.ok else None),
            "centre_row": g.centre[0] if g.ok else float("nan"),
            "centre_col": g.centre[1] if g.ok else float("nan")}


def spot_shape(plane, centre: tuple[float, float]) -> dict[str, float]:
    """Whether a 2-D PSF is a spot, from its azimuthal profile about ``centre``
    (row, column; pixels) above its background (the median of its border).

    Returns
    -------
    dict
        ``core_share``: the share of the energy within the first minimum of the profile
        (a spot: at least :data:`SPOT_CORE`); ``ring_radius`` and ``ring_width``: the
        radius of the profile's maximum beyond that minimum and its full width at half
        that maximum (pixels; NaN for a spot, or where the profile shows no ring).
    """
    p = np.asarray(plane, dtype=np.float64)
    border = np.concatenate([p[0], p[-1], p[1:-1, 0], p[1:-1, -1]])
    p = p - float(np.median(border))
    yy, xx = np.indices(p.shape)
    rr = np.hypot(yy - centre[0], xx - centre[1])
    half = min(p.shape) // 2
    r = np.rint(rr).astype(int)
    inside = r < half
    prof = (np.bincount(r[inside], p[inside], minlength=half)
            / np.maximum(np.bincount(r[inside], minlength=half), 1))
    k = 1  # the first minimum: where the profile first stops falling
    while k < half - 1 and prof[k + 1] < prof[k]:
        k += 1
    total = float(p[rr <= half].sum())
    share = float(p[rr <= k + 0.5].sum() / total) if total > 0 else float("nan")
    out = {"core_share": share, "ring_radius": float("nan"), "ring_width": float("nan")}
    if not share < SPOT_CORE or k >= half - 2:
        return out
    j = k + int(np.argmax(prof[k:]))
    top = prof[j]
    if top > 0:  # the ring: the run of radii about its maximum above half of it
        lo, hi = j, j
        while lo - 1 >= k and prof[lo - 1] >= top / 2:
            lo -= 1
        while hi + 1 < half and prof[hi + 1] >= top / 2:
            hi += 1
        out.update(ring_radius=float(j), ring_width=float(hi - lo + 1))
    return out


def spot_measures(plane) -> dict[str, float]:
    """:func:`lateral_measures` of a 2-D PSF, with :func:`spot_shape`: the widths and the
    ellipticity are NaN where the PSF is not a spot (a ring, a cross, a defocused disk),
    whose Gaussian FWHM would measure nothing a microscopist reads."""
    m = lateral_measures(plane)
    centre = (m["centre_row"], m["centre_col"])
    if not np.isfinite(centre[0]):
        q = np.clip(np.asarray(plane, np.float64), 0, None)
        yy, xx = np.indices(q.shape)
        w = max(float(q.sum()), 1e-300)
        centre = (float((q * yy).sum() / w), float((q * xx).sum() / w))
    shape = spot_shape(plane, centre)
    if not shape["core_share"] >= SPOT_CORE:
        m.update({n: float("nan") for n in LATERAL})
    return {**m, **shape}


def _from_covariance(cov) -> dict[str, float]:
    """The lateral measures of a 2 x 2 covariance (pixels^2), and its entries
    ``cov_rr``, ``cov_rc``, ``cov_cc``; NaN for None."""
    if cov is None or not np.all(np.isfinite(cov)):
        return {n: float("nan") for n in (*LATERAL, "angle", "cov_rr", "cov_rc", "cov_cc")}
    w, v = np.linalg.eigh(cov)
    major, minor = FWHM_PER_SIGMA * np.sqrt(np.clip(w[::-1], 0.0, None))
    angle = float(np.arctan2(v[1, 1], v[0, 1]))
    angle = angle + np.pi if angle <= -np.pi / 2 else (angle - np.pi if angle > np.pi / 2
                                                       else angle)
    return {"fwhm_lateral": float(np.sqrt(major * minor)),
            "fwhm_row": float(FWHM_PER_SIGMA * np.sqrt(max(cov[0, 0], 0.0))),
            "fwhm_col": float(FWHM_PER_SIGMA * np.sqrt(max(cov[1, 1], 0.0))),
            "fwhm_major": float(major), "fwhm_minor": float(minor),
            "ellipticity": float(1.0 - minor / major) if major > 0 else float("nan"),
            "angle": angle, "cov_rr": float(cov[0, 0]), "cov_rc": float(cov[0, 1]),
            "cov_cc": float(cov[1, 1])}


def _vertex(values: np.ndarray, k: int) -> float:
    """Sub-sample position of the extremum at ``k``: a parabola through ``k - 1, k,
    k + 1`` (``k`` itself at an end)."""
    if 0 < k < len(values) - 1 and np.all(np.isfinite(values[k - 1:k + 2])):
        a, b, c = values[k - 1], values[k], values[k + 1]
        den = a - 2 * b + c
        if den != 0:
            return float(k + np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    return float(k)


def peak_profile(psf, *, radius: float | None = None) -> np.ndarray:
    """Each plane's peak near the lateral centre, shape (Z,): the largest 3 x 3 mean
    within ``radius`` (default ``max(2, P / 4)``) pixels of the centre."""
    vol = np.asarray(psf, dtype=np.float64)
    _, p, q = vol.shape
    r = max(2.0, min(p, q) / 4.0) if radius is None else float(radius)
    yy, xx = np.indices((p, q))
    near = (yy - (p - 1) / 2) ** 2 + (xx - (q - 1) / 2) ** 2 <= r * r
    sm = ndi.uniform_filter(vol, size=(1, 3, 3), mode="nearest")
    return sm[:, near].max(axis=1)


def focal_plane(psf, *, radius: float | None = None) -> float:
    """The plane in focus of a 3D PSF (sub-plane): the highest peak near the lateral
    centre (:func:`peak_profile`), refined by a parabola."""
    prof = peak_profile(psf, radius=radius)
    return _vertex(-prof, int(np.argmax(prof)))


def _line_focus(z: np.ndarray, width: np.ndarray, k0: int) -> float:
    """The line focus of one axis (planes): the minimum of ``width`` (sampled at planes
    ``z``) nearest index ``k0`` (the focal plane), refined by a parabola through the
    squared widths within :data:`LINE_FOCUS_REACH` planes; NaN where fewer than 3 widths
    are finite or the minimum lies at an end of ``z`` (beyond what the stack shows)."""
    ok = np.isfinite(width)
    if ok.sum() < 3 or not ok[k0]:
        return float("nan")
    # 3-plane running mean of the finite widths (noise in one plane's fit is not a minimum)
    w = np.where(ok, width, 0.0)
    num = np.convolve(w, np.ones(3), "same")
    den = np.convolve(ok.astype(float), np.ones(3), "same")
    sm = np.where(ok, num / np.maximum(den, 1), np.inf)
    k = k0
    while True:  # steepest descent from focus to the nearest minimum
        nb = [j for j in (k - 1, k + 1) if 0 <= j < len(sm) and sm[j] < sm[k]]
        if not nb:
            break
        k = min(nb, key=lambda j: sm[j])
    # the smoothing moves the minimum of an uneven curve: the raw minimum beside it
    near = [j for j in (k - 1, k, k + 1) if 0 <= j < len(sm) and ok[j]]
    k = min(near, key=lambda j: width[j])
    if k in (0, len(sm) - 1):
        return float("nan")
    sel = np.arange(k - LINE_FOCUS_REACH, k + LINE_FOCUS_REACH + 1)
    sel = sel[(sel >= 0) & (sel < len(sm))]
    sel = sel[ok[sel]]
    if len(sel) < 3:
        return float(z[k])
    a, b, _ = np.polyfit(z[sel], width[sel] ** 2, 2)
    c = -b / (2 * a) if a > 0 else z[k]
    return float(np.clip(c, z[sel].min(), z[sel].max()))


def _axial_fwhm(prof: np.ndarray) -> float:
    """The axial FWHM (planes) of the profile through the centre: a Gaussian with an
    offset, refitted within :data:`CORE` FWHMs of its centre, where the profile reaches a
    FWHM beyond the centre on both sides; else, where it reaches the half-maximum points,
    a Gaussian with no offset (the PSF is background-free); else NaN."""
    nz = len(prof)
    if nz < 4:
        return float("nan")
    for offset in (True, False):
        g = fit_gaussian_1d(prof, offset=offset)
        if g.ok and CORE:
            near = np.abs(np.arange(nz) - g.centre) <= max(CORE * g.fwhm, 2.5)
            if near.sum() >= 5:
                g1 = fit_gaussian_1d(prof[near], np.flatnonzero(near).astype(float),
                                     offset=offset)
                g = g1 if g1.ok else g
        reach = g.fwhm if offset else g.fwhm / 2
        if g.ok and g.centre - reach >= 0 and g.centre + reach <= nz - 1:
            return g.fwhm
    return float("nan")


def psf_measures(psf) -> dict[str, float]:
    """The measures of one 3D PSF (planes and pixels).

    Parameters
    ----------
    psf : array_like of shape (Z, P, Q)
        A PSF or a bead's patch, plane ``z`` at index ``z``, laterally about the centre.

    Returns
    -------
    dict
        :data:`NAMES` and ``astigmatic_split_limit``, ``angle``: ``focal_plane``
        (planes from index 0, sub-plane), the lateral widths (pixels) on the plane in
        focus (interpolated between the two planes about it), ``fwhm_axial`` (planes),
        ``astigmatic_split`` (planes, ``z_col - z_row``); NaN where a fit failed or the
        stack cannot show the measure.
    """
    vol = np.asarray(psf, dtype=np.float64)
    if vol.ndim != 3 or vol.shape[0] < 1 or min(vol.shape[1:]) < 5:
        raise ValueError(f"`psf` must be a 3-D PSF (Z, P, Q) with planes of at least 5 x 5, "
                         f"got shape {vol.shape}.")
    nz = vol.shape[0]
    peaks = peak_profile(vol)
    k0 = int(np.argmax(peaks))
    z0 = _vertex(-peaks, k0)
    lo = int(np.clip(np.floor(z0), 0, nz - 1))
    hi = min(lo + 1, nz - 1)
    fits = {k: lateral_measures(vol[k]) for k in {lo, hi, k0}}
    t = z0 - lo

    def cov(m):
        return np.array([[m["cov_rr"], m["cov_rc"]], [m["cov_rc"], m["cov_cc"]]])

    # the covariance interpolated between the planes about focus (an ellipse turning
    # through focus is round between its line foci, not the mean of two ellipses)
    c = (1 - t) * cov(fits[lo]) + t * cov(fits[hi])
    lat = _from_covariance(c if np.all(np.isfinite(c)) else cov(fits[k0]))
    out = {"focal_plane": z0, **{n: lat[n] for n in (*LATERAL, "angle")}}
    # the axial profile through the centre fitted in focus
    cy, cx = fits[k0]["centre_row"], fits[k0]["centre_col"]
    if not np.isfinite(cy):
        cy, cx = (vol.shape[1] - 1) / 2, (vol.shape[2] - 1) / 2
    prof = np.array([ndi.map_coordinates(vol[k], [[cy], [cx]], order=1)[0] for k in range(nz)])
    out["fwhm_axial"] = _axial_fwhm(prof)
    # the line foci: the planes about focus that keep MIN_PEAK_SHARE of its peak
    keep = peaks >= MIN_PEAK_SHARE * peaks[k0]
    first = k0 - int(np.argmin(keep[k0::-1])) + 1 if not keep[:k0 + 1].all() else 0
    last = k0 + int(np.argmin(keep[k0:])) - 1 if not keep[k0:].all() else nz - 1
    zs = np.arange(first, last + 1)
    out["astigmatic_split_limit"] = float(last - first)
    out["astigmatic_split"] = float("nan")
    if len(zs) >= 3:
        per = [fits.get(k) or lateral_measures(vol[k]) for k in zs]
        zf = zs.astype(float)
        z_row = _line_focus(zf, np.array([m["fwhm_row"] for m in per]), k0 - first)
        z_col = _line_focus(zf, np.array([m["fwhm_col"] for m in per]), k0 - first)
        out["astigmatic_split"] = float(z_col - z_row)
    return out


def in_units(measures: dict[str, float], voxel_size) -> tuple[dict[str, float],
                                                                dict[str, str]]:
    """Measures in nm where the voxel size is known, and the unit of each.

    Parameters
    ----------
    measures : dict
        From :func:`psf_measures` or :func:`lateral_measures` (pixels and planes).
    voxel_size : tuple of float or None
        ``(dz, dy, dx)`` or ``(dy, dx)`` in µm; None keeps pixels and planes.

    Returns
    -------
    values, units : dict, dict
        A lateral width is scaled by the pixel size (square pixels: ``dy``), an axial
        length by ``dz``; ``focal_plane`` becomes the focus' depth from the first plane.
    """
    if voxel_size is None:
        return dict(measures), {n: UNITS_PX.get(n, "") for n in measures}
    vs = tuple(float(v) for v in voxel_size)
    dz, dy = (vs[0], vs[1]) if len(vs) == 3 else (float("nan"), vs[0])
    values, units = {}, {}
    for n, v in measures.items():
        unit = UNITS_PX.get(n, "")
        if unit == "px":
            values[n], units[n] = v * dy * 1000.0, "nm"
        elif unit == "planes" and np.isfinite(dz):
            values[n], units[n] = v * dz * 1000.0, "nm"
        else:
            values[n], units[n] = v, unit
    return values, units


#: The immersion index assumed from the NA where none is given: (largest NA, index) of
#: air, water and oil objectives (the common immersion of each range).
IMMERSION = ((0.95, 1.0), (1.27, 1.333), (float("inf"), 1.518))


def assumed_immersion(na: float) -> float:
    """The immersion index of the common objective of this NA (:data:`IMMERSION`)."""
    return next(n for top, n in IMMERSION if na <= top)


def diffraction_limit(na: float, wavelength: float, *,
                      refractive_index: float | None = None) -> dict[str, float]:
    """The widefield diffraction-limited FWHM, µm.

    Parameters
    ----------
    na : float
        Numerical aperture, > 0.
    wavelength : float
        Emission wavelength, µm (> 0).
    refractive_index : float, optional
        Of the immersion; default :func:`assumed_immersion` (air, water or oil).

    Returns
    -------
    dict
        ``lateral``: the Airy disk's FWHM ``0.514 lambda / NA``; ``axial``:
        ``0.886 lambda / (n - sqrt(n^2 - NA^2))`` (the paraxial-corrected widefield
        value). Divide a measured width by these for the ratio to the limit.
    """
    na, wavelength = float(na), float(wavelength)
    if not (np.isfinite(na) and na > 0):
        raise ValueError(f"`na` must be a positive number, got {na}.")
    if not (np.isfinite(wavelength) and wavelength > 0):
        raise ValueError(f"`wavelength` must be a positive number of µm, got {wavelength}.")
    n = refractive_index
    n = float(assumed_immersion(na) if n is None else n)
    if not (np.isfinite(n) and n >= na):
        raise ValueError(f"`refractive_index` must be at least the NA ({na}), got {n}.")
    return {"lateral": 0.514 * wavelength / na,
            "axial": 0.886 * wavelength / (n - np.sqrt(n * n - na * na))}


#: Where :func:`field_fwhm` measures a 2-D model: the centre and the four corners, each a
#: tenth of the field in from its edges (inside the beads' usual reach).
FIELD_POINTS = (("centre", 0.5, 0.5), ("top left", 0.1, 0.1), ("top right", 0.1, 0.9),
                ("bottom left", 0.9, 0.1), ("bottom right", 0.9, 0.9))


def field_fwhm(operator) -> dict[str, dict[str, float]]:
    """The lateral measures of a 2-D model's PSF at the centre and the corners.

    Parameters
    ----------
    operator
        Anything with ``image_shape`` (H, W) and ``psf_at(row, column)`` giving a 2-D PSF.

    Returns
    -------
    dict
        Place (:data:`FIELD_POINTS`) -> :func:`lateral_measures` plus ``row``,
        ``col`` (the position, pixels); widths in pixels.
    """
    h, w = operator.image_shape[-2:]
    out = {}
    for name, fy, fx in FIELD_POINTS:
        y, x = fy * (h - 1), fx * (w - 1)
        out[name] = {**spot_measures(operator.psf_at(y, x)), "row": y, "col": x}
    return out


def patch_fwhms(psfs) -> np.ndarray:
    """Each bead's own lateral FWHM (pixels; NaN where its fit failed or it is no spot:
    :func:`spot_measures`) from its patch (K, P, P): the field as the beads show it,
    where no model maps it."""
    return np.array([spot_measures(p)["fwhm_lateral"] for p in np.asarray(psfs)], float)


def fwhm_line(summary: dict[str, dict[str, float]], pixel_size: float | None = None, *,
              one_psf: str | None = None) -> str:
    """One line for a printout or a report: the FWHM at the centre and over the corners,
    in nm where ``pixel_size`` (µm) is known, else pixels. ``one_psf``: the model is one
    PSF for the whole field, and this says why, in place of the corners (which would
    repeat the centre as if the field had been mapped)."""
    scale, unit, fmt = (1000.0 * pixel_size, "nm", ".0f") if pixel_size else (1.0, "px",
                                                                             ".2f")
    c = summary["centre"]
    corners = [v["fwhm_lateral"] * scale for k, v in summary.items() if k != "centre"]
    corners = [v for v in corners if np.isfinite(v)]
    if not c.get("core_share", 1.0) >= SPOT_CORE:  # a ring, a cross, a disk: no Gaussian
        ring = (f"a ring of radius {c['ring_radius'] * scale:{fmt}} {unit}, width "
                f"{c['ring_width'] * scale:{fmt}} {unit}"
                if np.isfinite(c.get("ring_radius", np.nan)) else "no ring either")
        share = (f"its central lobe holds {100 * c['core_share']:.0f} % of its light"
                 if np.isfinite(c.get("core_share", np.nan))
                 else "its light reaches beyond the window")
        text = f"the PSF at the centre is not a spot ({ring}; {share}): no Gaussian FWHM"
    else:
        text = (f"FWHM (Gaussian fit with an offset): centre "
                f"{c['fwhm_lateral'] * scale:{fmt}} {unit} (rows "
                f"{c['fwhm_row'] * scale:{fmt}}, columns {c['fwhm_col'] * scale:{fmt}}, "
                f"ellipticity {c['ellipticity']:.2f})")
    if one_psf:
        text += f"; {one_psf}"
    elif corners:
        text += f"; corners {min(corners):{fmt}}-{max(corners):{fmt}} {unit}"
    return text


__all__ = ["FIELD_POINTS", "IMMERSION", "LATERAL", "LINE_FOCUS_REACH", "MIN_PEAK_SHARE",
           "NAMES", "SPOT_CORE", "UNITS_PX", "assumed_immersion", "diffraction_limit",
           "field_fwhm", "focal_plane", "fwhm_line", "in_units", "lateral_measures",
           "patch_fwhms", "peak_profile", "psf_measures", "spot_measures", "spot_shape"]
