"""Each bead's own focus, the field's focal surface, and the beads registered to it.

Beads on a slide do not all lie at one depth: a tilted coverslip, field curvature and
beads resting on one another put their foci on different planes. Averaging or
decomposing their 3D patches on one common plane then mixes a bead's focal offset into
the PSF (a bead focused three planes away widens the mean's axial profile). So:

1. **Each bead's focus** (:func:`axial_centres`): the sub-plane maximum of its axial
   profile, its peak above the local background on each plane
   (:func:`~napari_psfspace.core.beads.focus.bead_peaks`), lightly smoothed. The
   profile's half-maximum width comes with it. A profile whose half maximum is not
   reached on both sides inside the stack gives no focus (NaN).
2. **The focal surface** (:func:`fit_focal_surface`): a least-squares surface through
   the foci over the field: a constant, a tilt in row and column, and a radial
   curvature about the field's centre (fewer terms with fewer beads), refitted without
   the beads far off it. A bead is far off when its distance exceeds both four robust
   standard deviations of the distances and the beads' median axial half-maximum
   width: its PSF at the surface's plane is then below half its peak.
3. **Registration** (:func:`shift_planes`): each bead's patch is moved along z by its
   focus's offset from the surface (a cubic B-spline, sub-plane), so that every bead
   is seen as if it lay on the surface. The surface itself (tilt, curvature) stays in
   the patches: a deconvolution needs it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

#: Beads needed for each surface: a radial curvature from 8, a tilt from 5, else a
#: constant focus (each term needs beads to spare, or the surface follows their scatter).
SURFACE_TERMS = ((8, ("constant", "tilt_row", "tilt_col", "curvature")),
                 (5, ("constant", "tilt_row", "tilt_col")),
                 (1, ("constant",)))
#: Beads with a focus inside the stack needed to judge a bead without one.
MIN_SURFACE_BEADS = 5
#: A bead is off the surface beyond this many robust standard deviations of the
#: distances (and beyond the beads' median axial half-maximum width).
OFF_SURFACE_SD = 4.0


def _peak_vertex(p: np.ndarray, k: int) -> float:
    """The sub-plane position of the maximum at ``k`` of a sampled profile: the vertex of
    a parabola through the logarithms of ``k - 1, k, k + 1`` (exact for a Gaussian), or
    through the values where one of them is not positive."""
    a, b, c = p[k - 1], p[k], p[k + 1]
    if min(a, b, c) > 0:
        a, b, c = np.log(a), np.log(b), np.log(c)
    den = a - 2 * b + c
    return float(k + (0.5 * (a - c) / den if den < 0 else 0.0))


def axial_centres(profiles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The focus and the half-maximum width of each axial profile.

    Parameters
    ----------
    profiles : ndarray of shape (K, Z)
        Each bead's peak above its local background on each plane.

    Returns
    -------
    centre : ndarray of shape (K,)
        The plane of the profile's maximum, sub-plane: the vertex of a parabola through
        the logarithms of the three planes about the maximum of the profile smoothed by
        ``[1, 2, 1] / 4`` (the noise of one plane does not move it a plane), in planes
        from the first. The brightest plane is what a microscopist calls focus; where
        spherical aberration gives the profile a tail on one side, the midpoint of its
        half-maximum crossings would lie planes away from it. NaN where the peak is not
        positive or its half maximum is not crossed inside the stack on both sides.
    width : ndarray of shape (K,)
        The distance between the half-maximum crossings, planes, linear between planes
        (NaN with the centre).
    """
    p = np.asarray(profiles, np.float64)
    k, z = p.shape
    centre = np.full(k, np.nan)
    width = np.full(k, np.nan)
    smooth = p.copy()
    if z >= 3:
        smooth[:, 1:-1] = 0.25 * p[:, :-2] + 0.5 * p[:, 1:-1] + 0.25 * p[:, 2:]
    for i in range(k):
        top = int(np.argmax(p[i]))
        half = 0.5 * p[i, top]
        if not half > 0:
            continue
        below = p[i] < half
        left = np.flatnonzero(below[:top])
        right = np.flatnonzero(below[top:])
        if not len(left) or not len(right):
            continue  # the half maximum lies beyond the stack on one side
        a, b = left[-1], top + right[0]
        zl = a + (half - p[i, a]) / (p[i, a + 1] - p[i, a])
        zr = b - 1 + (p[i, b - 1] - half) / (p[i, b - 1] - p[i, b])
        width[i] = zr - zl
        ks = int(np.argmax(smooth[i, a + 1:b])) + a + 1  # the smoothed peak, inside
        centre[i] = _peak_vertex(smooth[i], ks) if 0 < ks < z - 1 else float(ks)
    return centre, width


@dataclass
class FocalSurface:
    """A smooth focal surface over the field, in planes.

    Attributes
    ----------
    terms : tuple of str
        The surface's terms (``constant``, ``tilt_row``, ``tilt_col``, ``curvature``).
    coefficients : ndarray of shape (len(terms),)
        Planes per unit of the field coordinates: ``u = (row - cy) / R``, ``v = (col -
        cx) / R``, ``R`` half the field's diagonal; ``curvature`` multiplies ``u^2 + v^2``.
    shape : (int, int)
        The field, pixels.
    offsets : ndarray of shape (K,)
        Each bead's focus less the surface at its position, planes (NaN: no focus).
    off : ndarray of shape (K,), bool
        Beads far off the surface (module notes).
    limit : float
        The distance beyond which a bead is off, planes.
    sd : float
        The robust standard deviation of the kept beads' distances, planes.
    """

    terms: tuple[str, ...]
    coefficients: np.ndarray
    shape: tuple[int, int]
    offsets: np.ndarray
    off: np.ndarray
    limit: float
    sd: float
    n_used: int = 0
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def _design(self, positions) -> np.ndarray:
        return design(positions, self.shape, self.terms)

    def __call__(self, positions) -> np.ndarray:
        """The surface's plane at ``positions`` (row, column), shape (K, 2) -> (K,)."""
        return self._design(positions) @ self.coefficients

    def summary(self, z_step: float | None = None) -> dict:
        """Tilt and curvature over the field, in planes and, with the plane spacing
        ``z_step`` (µm), in µm: ``tilt`` is the rise of the plane part across the
        field's diagonal, ``curvature`` the sag from the centre to a corner."""
        c = dict(zip(self.terms, self.coefficients, strict=True))
        tilt = 2.0 * float(np.hypot(c.get("tilt_row", 0.0), c.get("tilt_col", 0.0)))
        curv = float(c.get("curvature", 0.0))
        out = {"terms": list(self.terms), "n_beads": int(self.n_used),
               "n_off": int(self.off.sum()), "sd_planes": float(self.sd),
               "limit_planes": float(self.limit), "tilt_planes": tilt,
               "curvature_planes": curv,
               "centre_plane": float(c.get("constant", np.nan)),
               "coefficients": [float(v) if np.isfinite(v) else None
                                for v in self.coefficients]}
        if z_step:
            out.update(tilt_um=tilt * z_step, curvature_um=curv * z_step,
                       sd_um=float(self.sd) * z_step)
        # JSON holds no NaN or infinity: None for a value not measured
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                for k, v in out.items()}


def design(positions, shape, terms) -> np.ndarray:
    """The surface's design matrix at ``positions`` (row, column), (K, len(terms))."""
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    h, w = shape
    scale = 0.5 * float(np.hypot(h, w))
    u = (pos[:, 0] - (h - 1) / 2) / scale
    v = (pos[:, 1] - (w - 1) / 2) / scale
    cols = {"constant": np.ones(len(pos)), "tilt_row": u, "tilt_col": v,
            "curvature": u * u + v * v}
    return np.column_stack([cols[t] for t in terms])


def fit_focal_surface(positions, foci, widths, shape, *, depth: int | None = None,
                      rounds: int = 3) -> FocalSurface:
    """The focal surface through the beads' foci (module notes).

    Parameters
    ----------
    positions : ndarray of shape (K, 2)
        Lateral centres (row, column), pixels.
    foci : ndarray of shape (K,)
        Each bead's focus, planes (NaN: none inside the stack). A bead with none is not
        fitted. It is off the surface where the surface, fitted to
        :data:`MIN_SURFACE_BEADS` beads or more, puts its focus inside the stack by
        more than the limit from either end (``depth`` given); else it is kept, not
        moved (a field whose focus leaves the stack at its corners keeps its corners).
    widths : ndarray of shape (K,)
        Each bead's axial half-maximum width, planes.
    shape : (int, int)
        The field, pixels.
    depth : int, optional
        The stack's planes (to judge the beads without a focus).
    rounds : int
        Refits without the beads off the surface.

    Returns
    -------
    FocalSurface
        With no focus at all, a constant surface at NaN and no bead off.
    """
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    foci = np.asarray(foci, np.float64)
    widths = np.asarray(widths, np.float64)
    finite = np.isfinite(foci)
    off = np.zeros(len(foci), bool)
    width = float(np.nanmedian(widths)) if np.isfinite(widths).any() else 0.0
    terms, coef, sd, limit = ("constant",), np.array([np.nan]), 0.0, np.inf
    for _ in range(max(int(rounds), 1)):
        use = finite & ~off
        n = int(use.sum())
        if n == 0:
            break
        terms = next(t for need, t in SURFACE_TERMS if n >= need)
        a = design(pos[use], shape, terms)
        coef = np.linalg.lstsq(a, foci[use], rcond=None)[0]
        dist = foci - design(pos, shape, terms) @ coef
        d = dist[use]
        sd = float(1.4826 * np.median(np.abs(d - np.median(d)))) if n >= 3 else 0.0
        limit = max(OFF_SURFACE_SD * sd, width) if n >= 3 else np.inf
        new = finite & (np.abs(dist) > limit)
        if np.array_equal(new, off):
            break
        off = new
    surface = FocalSurface(terms, np.asarray(coef, np.float64), tuple(shape),
                           np.full(len(foci), np.nan), off, float(limit), float(sd),
                           int((finite & ~off).sum()), pos)
    if len(foci):
        surface.offsets = np.where(finite, foci - surface(pos), np.nan)
    if depth is not None and surface.n_used >= MIN_SURFACE_BEADS and (~finite).any():
        # a bead with no focus inside the stack where the surface puts its focus well
        # inside it (farther than the limit from either end) is not where the others are
        at = surface(pos[~finite])
        inside = (at > limit) & (at < int(depth) - 1 - limit)
        surface.off[np.flatnonzero(~finite)[inside]] = True
    return surface


def _rounded(values, digits: int = 2) -> list:
    return [round(float(v), digits) if np.isfinite(v) else None for v in values]


def focus_record(foci, plane: int, surface: FocalSurface,
                 voxel_size: tuple[float, float, float] | None = None) -> dict:
    """The model file's record of the beads' foci and the focal surface (JSON: None
    for a focus not measured).

    ``bead_focus_planes``: each used bead's focus, planes from the first;
    ``bead_focal_shift_planes``: the same less the bead plane ``plane``;
    ``focal_surface``: :meth:`FocalSurface.summary` (µm with ``voxel_size``);
    ``off_focus_beads``: the beads left out, their positions and distances (planes).
    """
    foci = np.asarray(foci, np.float64)
    dz = voxel_size[0] if voxel_size else None
    off = np.flatnonzero(surface.off)
    return {"bead_focus_planes": _rounded(foci),
            "bead_focal_shift_planes": _rounded(foci - plane),
            "focal_surface": surface.summary(dz),
            "off_focus_beads": [{"position": _rounded(surface.positions[k]),
                                 "offset_planes": _rounded([surface.offsets[k]])[0]}
                                for k in off]}


def focus_line(surface: FocalSurface, voxel_size=None) -> str:
    """One line on the focal surface: its tilt and curvature, the beads' scatter about
    it, and the beads left out."""
    dz = voxel_size[0] if voxel_size else None
    s = surface.summary(dz)
    if s["centre_plane"] is None:
        return "no bead's focus is inside the stack: the beads are not registered in z"

    def length(planes: float) -> str:
        return f"{planes * dz * 1000:.0f} nm" if dz else f"{planes:.2f} planes"

    parts = [f"focal surface from {s['n_beads']} beads: centre plane {s['centre_plane']:.2f}"]
    if s["sd_planes"] is None or s["limit_planes"] is None:
        return parts[0] + " (too few beads to measure their scatter about it)"
    if "tilt_row" in surface.terms:
        parts.append(f"tilt {length(s['tilt_planes'])} across the diagonal")
    if "curvature" in surface.terms:
        parts.append(f"curvature {length(s['curvature_planes'])} centre to corner")
    parts.append(f"beads scattered {length(s['sd_planes'])} (robust sd) about it")
    line = ", ".join(parts)
    far = int(np.sum(surface.off & np.isfinite(surface.offsets)))
    if far:
        line += f"; {far} bead(s) more than {length(s['limit_planes'])} off it left out"
    if s["n_off"] > far:
        line += (f"; {s['n_off'] - far} bead(s) whose focus is not inside the stack left "
                 "out")
    return line


def shift_planes(psf: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Each patch moved along its first axis by ``-shifts[k]`` planes, so that what lay
    on plane ``z + shifts[k]`` lies on ``z``: a cubic B-spline along z, zero beyond
    the patch (planes beyond the stack hold nothing).

    Parameters
    ----------
    psf : ndarray of shape (K, Zp, P, P)
    shifts : ndarray of shape (K,)
        Planes (0: unchanged; NaN counts as 0).

    Returns
    -------
    ndarray of the same shape and dtype
    """
    psf = np.asarray(psf)
    out = np.array(psf, copy=True)
    for k, s in enumerate(np.nan_to_num(np.asarray(shifts, np.float64))):
        if s == 0:
            continue
        coef = ndi.spline_filter1d(psf[k], order=3, axis=0, mode="grid-constant")
        n = int(np.floor(s))
        f = s - n
        # B-spline weights of the four coefficients about z + s
        w = ((1 - f) ** 3 / 6, (3 * f ** 3 - 6 * f ** 2 + 4) / 6,
             (-3 * f ** 3 + 3 * f ** 2 + 3 * f + 1) / 6, f ** 3 / 6)
        acc = np.zeros_like(coef)
        zp = coef.shape[0]
        for j, wj in zip(range(-1, 3), w, strict=True):
            m = n + j  # acc[z] += wj * coef[z + m]
            lo, hi = max(0, -m), min(zp, zp - m)
            if lo < hi:
                acc[lo:hi] += wj * coef[lo + m:hi + m]
        out[k] = acc
    return out


__all__ = ["MIN_SURFACE_BEADS", "OFF_SURFACE_SD", "SURFACE_TERMS", "FocalSurface",
           "axial_centres", "design", "fit_focal_surface", "focus_line", "focus_record",
           "shift_planes"]
