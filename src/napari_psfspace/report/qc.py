"""A microscope's QC record from one bead z-stack: the numbers of ``qc.json``.

From a 3D estimate (:func:`~napari_psfspace.core.volume.iter_estimate_operator_3d`,
beads registered to the focal surface) the record holds:

* the PSF at the field's centre: lateral FWHM (rows, columns, major, minor), axial
  FWHM, ellipticity, astigmatic split, by the measures napari-psf-analysis quotes (a
  2-D Gaussian in focus, a 1-D Gaussian along the axis: the QUAREP-LiMi working group 5
  practice), each fitted to every bead's own pixels and taken to the centre by a plane
  over the field (:func:`centre_value`), the model's PSF there beside it (the model is
  learnt from patches re-sampled to each bead's sub-pixel centre, which widens a PSF
  sampled near Nyquist); ``centre_fwhm_lateral_nm`` and ``centre_fwhm_axial_nm`` at the
  top level;
* the same measures on an 8 x 8 grid of the field (``maps``) and their range;
* the focal surface (tilt and curvature, µm) and the beads left off it;
* theory, where NA and wavelength are given: Abbe's widths
  (:func:`~napari_psfspace.core.common.measures.diffraction_limit`) and those of an
  aberration-free scalar pupil PSF from the project's own optics at the stack's
  sampling, measured the same way as the beads;
* checks against tolerances (ratio to theory, ellipticity, the focal surface's rise
  over the field against the axial FWHM), each with its value, limit and verdict;
* sampling (Nyquist) and saturation warnings; the beads used and refused, each with
  its reason; the model's own verdict (held-out beads, field against one PSF).

:func:`qc_record` builds it; :mod:`.qc_page` writes the page.
"""

from __future__ import annotations

import numpy as np

from ..core.beads.detect import KEPT, STATUS_MEANING
from ..core.common.measures import (
    assumed_immersion,
    diffraction_limit,
    in_units,
    psf_measures,
)
from ..core.volume.measures import direct_bead_measures, measure_maps, model_measures

#: Version of the record's layout (``qc.json``'s ``version``).
QC_VERSION = 1
#: Default tolerances: the measured FWHM over the theoretical one, the ellipticity, and
#: the focal surface's rise over the field (peak to valley) over the axial FWHM.
TOLERANCES = {"lateral_ratio": 1.5, "axial_ratio": 1.5, "ellipticity": 0.2,
              "field_flatness": 1.0}
#: A lateral FWHM sampled by fewer pixels than this is below Nyquist for a Gaussian fit.
MIN_PIXELS_PER_FWHM = 2.0


def _f(v, digits: int = 1):
    return round(float(v), digits) if v is not None and np.isfinite(v) else None


def pupil_theory(na: float, wavelength_um: float, index: float, voxel_size,
                 n_planes: int = 41, size: int = 33) -> dict:
    """The FWHM of an aberration-free scalar pupil PSF (the project's optics) at the
    stack's sampling ``(dz, dy, dx)`` µm, measured as the beads are: nm."""
    from ..core.simulation.focus import defocus_zernike
    from ..core.simulation.optics import Optics, simulate_psf

    dz, dy, _ = voxel_size
    optics = Optics(na=float(na), wavelength=float(wavelength_um), pixel_size=float(dy))
    z = (np.arange(n_planes) - n_planes // 2) * dz
    vol = np.stack([simulate_psf(defocus_zernike(float(zk), optics, index=index)[0],
                                 optics=optics, size=size) for zk in z])
    m, _ = in_units(psf_measures(vol), voxel_size)
    return {"lateral_nm": _f(m["fwhm_lateral"]), "axial_nm": _f(m["fwhm_axial"])}


def _nyquist(na, wavelength_um, index, voxel_size, centre_px) -> list[str]:
    out = []
    if voxel_size is not None and na and wavelength_um:
        dz, dy, _ = voxel_size
        lat = wavelength_um / (4 * na)
        cos = np.sqrt(max(index ** 2 - na ** 2, 0.0)) / index
        ax = wavelength_um / (2 * index * (1 - cos))
        if dy > lat:
            out.append(f"pixels of {dy * 1000:.0f} nm are coarser than Nyquist for NA "
                       f"{na:g} at {wavelength_um * 1000:.0f} nm ({lat * 1000:.0f} nm): "
                       "lateral widths read wider than the optics'")
        if dz > ax:
            out.append(f"planes {dz * 1000:.0f} nm apart are coarser than axial Nyquist "
                       f"({ax * 1000:.0f} nm)")
    lat_px = centre_px.get("fwhm_lateral", np.nan)
    if np.isfinite(lat_px) and lat_px < MIN_PIXELS_PER_FWHM:
        out.append(f"the lateral FWHM spans {lat_px:.2f} pixels, fewer than "
                   f"{MIN_PIXELS_PER_FWHM:g}: a Gaussian fit to it is unreliable")
    return out


def _saturation(meta: dict, dtype: str, stack_max: float) -> list[str]:
    out = []
    sat = meta.get("saturation") or {}
    n = int((meta.get("bead_counts") or {}).get("saturated", 0))
    if n:
        out.append(f"{n} bead(s) saturated (a clipped core), left out of the model")
    if np.dtype(dtype).kind in "ui" and stack_max >= np.iinfo(np.dtype(dtype)).max:
        out.append(f"the stack reaches its type's largest value ({stack_max:g}, {dtype}): "
                   "some pixels are clipped" + ("" if n else ", none in a bead's core"))
    elif sat.get("clipped_pixels"):
        out.append(f"{sat['clipped_pixels']} pixels at the clipping level")
    return out


def _check(name, value, limit, unit, why, higher_fails=True) -> dict:
    ok = None
    if value is not None and limit is not None and np.isfinite(value):
        ok = bool(value <= limit) if higher_fails else bool(value >= limit)
    return {"name": name, "value": _f(value, 3), "limit": limit, "unit": unit,
            "pass": ok, "why": why}


def centre_value(positions, values, shape) -> float:
    """A measure at the field's centre from the beads' own values: a plane (a constant
    and a tilt) fitted over the field to five beads or more, refitted without those
    beyond four robust standard deviations of it; the median of fewer. NaN without a
    finite value."""
    from ..core.volume.focal_surface import design

    v = np.asarray(values, float)
    ok = np.isfinite(v)
    if ok.sum() == 0:
        return float("nan")
    if ok.sum() < 5:
        return float(np.median(v[ok]))
    terms = ("constant", "tilt_row", "tilt_col")
    a = design(np.asarray(positions, float)[ok], shape, terms)
    coef = np.linalg.lstsq(a, v[ok], rcond=None)[0]
    res = v[ok] - a @ coef
    sd = 1.4826 * np.median(np.abs(res - np.median(res)))
    keep = np.abs(res) <= 4 * sd if sd > 0 else np.ones(len(res), bool)
    if 3 <= keep.sum() < len(res):
        coef = np.linalg.lstsq(a[keep], v[ok][keep], rcond=None)[0]
    return float(coef[0])  # the constant: the value at the field's centre


def surface_rise(surface, n: int = 9) -> float:
    """Peak to valley of a focal surface over an ``n x n`` grid of its field, planes; NaN
    for a constant surface (too few beads to fit a tilt)."""
    if surface is None or "tilt_row" not in surface.terms:
        return float("nan")
    h, w = surface.shape
    grid = np.stack(np.meshgrid(np.linspace(0, h - 1, n), np.linspace(0, w - 1, n),
                                indexing="ij"), -1).reshape(-1, 2)
    z = surface(grid)
    return float(np.max(z) - np.min(z))


def qc_record(estimation, stack, *, voxel_size=None, sampling_from: str = "unknown",
              na: float | None = None, wavelength_nm: float | None = None,
              immersion_index: float | None = None, tolerances: dict | None = None,
              source: str = "", diagnosis=None) -> dict:
    """The QC record of a 3D estimate (module notes).

    Parameters
    ----------
    estimation : Estimation3D
    stack : ndarray of shape (Z, H, W)
        The stack it was learnt from.
    voxel_size : (float, float, float), optional
        ``(dz, dy, dx)``, µm; without it lengths are in pixels and planes and the
        ``_nm`` values are None.
    sampling_from : str
        Where the voxel size came from ("file", "given", "unknown").
    na, wavelength_nm, immersion_index : float, optional
        The optics, for theory and Nyquist (the index defaults from the NA).
    tolerances : dict, optional
        Overrides of :data:`TOLERANCES`.
    source : str
        The stack's file name.
    diagnosis : Diagnosis, optional
        The 2-D diagnosis of the best-focus slice
        (:func:`~napari_psfspace.core.diagnosis.loop.iter_diagnose`): its verdict and the
        effects it added go in the record.

    Returns
    -------
    dict
        JSON-ready (None for a value not measured).
    """
    from ..core.common.version import software_string

    tol = {**TOLERANCES, **(tolerances or {})}
    op = estimation.operator
    meta = op.metadata
    depth, h, w = op.image_shape
    centre = (np.array([h, w], float) - 1) / 2
    model_px = {k: float(v[0]) for k, v in model_measures(op, centre[None]).items()}
    model_nm, units = in_units(model_px, voxel_size)
    inl = estimation.basis.inliers
    direct = direct_bead_measures(stack, estimation)
    positions = estimation.patches.centers[inl]
    c_px = {k: centre_value(positions, direct[k], (h, w)) for k in model_px}
    c_nm, _ = in_units(c_px, voxel_size)
    ys, xs, maps = measure_maps(op, 8, 8)
    lam, index_from, index, theory = _theory(voxel_size, na, wavelength_nm, immersion_index)
    patches = estimation.patches.subset(inl)
    surface = meta.get("focal_surface") or {}
    checks = _checks(estimation, voxel_size, tol, c_px, c_nm, theory)
    warnings, status, refused = _warnings_and_refused(
            estimation, stack, voxel_size, na, meta, c_px, lam, index)
    held, verdict = _model_verdict(meta)

    def in_nm(name):
        return _f(c_nm[name]) if voxel_size is not None and units[name] == "nm" else None

    field = _field_summary(voxel_size, maps)
    return {
        "format": "napari-psfspace QC record", "version": QC_VERSION,
        "software": software_string(), "source": source,
        "stack_shape": [int(depth), int(h), int(w)],
        "sampling": {"pixel_size_nm": _f(voxel_size[1] * 1000) if voxel_size else None,
                     "z_step_nm": _f(voxel_size[0] * 1000) if voxel_size else None,
                     "from": sampling_from},
        "optics": {"na": na, "wavelength_nm": wavelength_nm, "immersion_index": index,
                   "immersion_index_from": index_from if index else None},
        "centre_fwhm_lateral_nm": in_nm("fwhm_lateral"),
        "centre_fwhm_axial_nm": in_nm("fwhm_axial"),
        "centre": {name: {"value": _f(c_nm[name], 3), "model": _f(model_nm[name], 3),
                          "unit": units[name]} for name in c_nm},
        "theory": theory, "tolerances": tol, "checks": checks,
        "passed": (all(c["pass"] for c in checks if c["pass"] is not None)
                   if any(c["pass"] is not None for c in checks) else None),
        "field": field, "maps": {"rows_px": [_f(v, 2) for v in ys],
                                 "cols_px": [_f(v, 2) for v in xs],
                                 **{k: [[_f(v, 4) for v in row] for row in arr]
                                    for k, arr in maps.items()}},
        "focal_surface": surface, "off_focus_beads": meta.get("off_focus_beads", []),
        "warnings": warnings,
        "beads": {"detected": int(len(status)), "used": int(inl.sum()),
                  "counts": meta.get("bead_counts", {}), "refused": refused},
        "model": {"n_psf": int(op.n_psf), "plane": int(op.plane),
                  "field_model": meta.get("field_model", "space-varying"),
                  "field_model_reason": meta.get("field_model_reason"),
                  "heldout": held, "verdict": verdict},
        "average_psf": {"n_beads": int(len(patches))},
        "per_bead": bead_rows(estimation, direct, voxel_size),
        "diagnosis": None if diagnosis is None else diagnosis_record(
            diagnosis, int(meta.get("focus_slice", op.plane))),
    }


def _theory(voxel_size, na, wavelength_nm, immersion_index):
    """The immersion index (given, or assumed from the NA) and the widths theory gives (Abbe's, and
    a pupil PSF's at this sampling), None without the NA and wavelength.
    """
    lam = wavelength_nm / 1000.0 if wavelength_nm else None
    index, index_from = immersion_index, "given"
    if na and not index:
        index, index_from = assumed_immersion(na), "assumed from the NA"
    theory = None
    if na and lam:
        abbe = diffraction_limit(na, lam, refractive_index=index)
        theory = {"abbe": {"lateral_nm": _f(abbe["lateral"] * 1000),
                           "axial_nm": _f(abbe["axial"] * 1000)}}
        if voxel_size is not None:
            theory["pupil_psf"] = pupil_theory(na, lam, index, voxel_size)
    return lam, index_from, index, theory


def _checks(estimation, voxel_size, tol, c_px, c_nm, theory):
    """The pass/fail checks: the centre's widths against theory, its ellipticity and the focal
    surface's rise against the depth of focus.
    """
    checks = []
    ref = (theory or {}).get("pupil_psf") or (theory or {}).get("abbe")
    lat_nm = c_nm["fwhm_lateral"] if voxel_size is not None else None
    ax_nm = c_nm["fwhm_axial"] if voxel_size is not None else None
    if ref and lat_nm is not None:
        checks.append(_check("lateral FWHM / theory", lat_nm / ref["lateral_nm"],
                             tol["lateral_ratio"], "", "the PSF at the field's centre "
                             "against the theoretical one"))
        checks.append(_check("axial FWHM / theory", ax_nm / ref["axial_nm"],
                             tol["axial_ratio"], "", "the same along the axis"))
    checks.append(_check("ellipticity", c_px["ellipticity"], tol["ellipticity"], "",
                         "1 - minor / major width at the field's centre"))
    rise = surface_rise(estimation.surface)
    if np.isfinite(c_px["fwhm_axial"]) and c_px["fwhm_axial"] > 0:
        checks.append(_check("focal surface rise / axial FWHM", rise / c_px["fwhm_axial"],
                             tol["field_flatness"], "", "how far focus moves over the "
                             "field (peak to valley of the focal surface through the "
                             "beads' foci) against the depth of focus"
                             + ("" if np.isfinite(rise) else
                                "; not judged: too few beads to fit a tilt")))
    return checks


def _warnings_and_refused(estimation, stack, voxel_size, na, meta, c_px, lam, index):
    """The warnings (sampling, saturation, one PSF for the field) and the beads refused, with why.
    """
    warnings = _nyquist(na, lam, index or 1.0, voxel_size, c_px)
    warnings += _saturation(meta, meta.get("image_dtype", "float32"), float(np.max(stack)))
    if meta.get("field_model") == "shift-invariant":
        warnings.append("one PSF for the whole field: " + meta.get("field_model_reason", ""))
    status = estimation.beads.status
    refused = [{"row": _f(p[0], 2), "col": _f(p[1], 2), "status": str(s),
                "reason": STATUS_MEANING.get(str(s), str(s))}
               for p, s in zip(estimation.beads.positions, status, strict=True) if s != KEPT]
    refused.sort(key=lambda x: (x["status"], x["row"] or 0.0, x["col"] or 0.0))
    return warnings, status, refused


def _model_verdict(meta):
    """The model's own check in words: its held-out residual against one PSF's."""
    held = meta.get("heldout") or {}
    if held.get("n_beads"):
        verdict = (f"on {held['n_beads']} held-out beads the model's residual is "
                   f"{held['residual_median']:.3f}, {held['over_floor']:.2f}x their noise "
                   f"floor; one 3D PSF for the field leaves {held['single_median']:.3f}: "
                   + ("the field model is kept" if held.get("field_wins")
                      else "one PSF is kept"))
    else:
        verdict = "not scored on held-out beads (fewer than 10 beads)"
    return held, verdict


def _field_summary(voxel_size, maps):
    """Each map's median, least and greatest value over the field, in the record's units."""
    field = {}
    for name, arr in maps.items():
        seen = arr[np.isfinite(arr)]  # none: a measure the field does not allow
        vals, u = in_units({name: float(np.median(seen)) if seen.size else np.nan},
                           voxel_size)
        lo, _ = in_units({name: float(seen.min()) if seen.size else np.nan}, voxel_size)
        hi, _ = in_units({name: float(seen.max()) if seen.size else np.nan}, voxel_size)
        field[name] = {"median": _f(vals[name], 3), "min": _f(lo[name], 3),
                       "max": _f(hi[name], 3), "unit": u[name]}
    return field


def diagnosis_record(diagnosis, focus_slice: int) -> dict:
    """What the report says of a 2-D diagnosis: its verdict, the effects it tried and
    added, the held-out error before and after."""
    v = diagnosis.verdict
    return {"slice": focus_slice, "level": v.level, "headline": v.headline,
            "ratio": _f(v.ratio, 3), "added": list(diagnosis.added),
            "tested": list(v.tested), "unanswered": list(v.unanswered),
            "error_before": _f(diagnosis.error_before, 4),
            "error_after": _f(diagnosis.error_after, 4)}


def average_psf(estimation) -> tuple[np.ndarray, np.ndarray]:
    """The mean and the standard deviation over the field of the beads' registered,
    normalised 3D patches (those in the model), each (Zp, P, P)."""
    p = estimation.patches.psf[estimation.basis.inliers]
    return p.mean(axis=0), (p.std(axis=0, ddof=1) if len(p) > 1 else np.zeros(p.shape[1:]))


def bead_rows(estimation, direct: dict, voxel_size=None) -> list[dict]:
    """The per-bead CSV's rows: position, own focus and distance from the focal surface
    (planes), and every measure fitted to its own pixels (``direct``, from
    :func:`~napari_psfspace.core.volume.measures.direct_bead_measures`; nm with a voxel
    size)."""
    from ..core.volume.measures import measure_table

    inl = estimation.basis.inliers
    patches = estimation.patches.subset(inl)
    rows = measure_table(direct, patches.centers, voxel_size)
    focus = np.asarray(estimation.bead_focus)[inl]
    surface = estimation.surface
    offset = focus - surface(patches.centers)
    for row, f, o in zip(rows, focus, offset, strict=True):
        row["focus_plane"] = _f(f, 3)
        row["offset_from_surface_planes"] = _f(o, 3)
    return rows


__all__ = ["MIN_PIXELS_PER_FWHM", "QC_VERSION", "TOLERANCES", "average_psf", "bead_rows",
           "centre_value", "diagnosis_record", "pupil_theory", "qc_record", "surface_rise"]
