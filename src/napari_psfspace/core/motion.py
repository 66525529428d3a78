"""Motion blur of a calibration image: find it, report it, and remove it on request.

A stage or sample that moves by ``L`` pixels along a direction ``u`` during the exposure
convolves every bead with the same line segment. Its transfer function is
``sinc(L k.u)`` (:func:`motion_transfer`): it vanishes on the straight lines
``k.u = +-1/L, +-2/L, ...`` of the Fourier plane. No lens makes such zeros: an objective's
transfer falls smoothly to its cutoff, and the zeros that strong defocus or spherical
aberration bring are rings, not straight lines. :func:`detect_motion` looks for one
straight zero line, common to all beads, inside the band where the beads' mean signal
stands above its noise. It reports the smear's length and direction, or says that no
motion long enough to be seen is there (a smear whose first zero lies beyond that band
cannot be told from the optics: :attr:`Motion.min_visible_px`).

Motion blurs a sample imaged the same way just as much, so the learnt operator is right
*for that exposure*; a calibration meant for other exposures should remove it
(``remove_motion=True``, :func:`remove_motion`) once the user knows the sample was still
while imaging, or image the beads again.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import fft as sfft

#: Fewest beads tested (two halves estimate the noise, four quarters must agree).
MIN_BEADS = 8
#: Directions tried, degrees (0: along the columns, 90: along the rows).
ANGLE_STEP = 2.0
#: A dip is a zero line when the profile there is below this fraction of the geometric
#: mean of its two flanks (a sinc's zero with flanks at a third of the way to the
#: neighbouring lobes: < 0.05 without noise) ...
MAX_DIP_RATIO = 0.3
#: ... by at least this many standard errors of the profile there,
MIN_DIP_Z = 6.0
#: ... and still below this ratio in every quarter of the beads (it is common to all of
#: them), while the perpendicular direction shows no dip below it there (a line, not a
#: ring).
MAX_CHECK_RATIO = 0.5
#: The band where the beads' mean signal power exceeds this many standard errors ...
BAND_Z = 5.0
#: ... and this fraction of its zero-frequency value: beyond the optics' cutoff the mean
#: power of windowed, re-sampled patches sits on a floor of ~1e-4 (interpolation, window
#: leakage, background errors) that is measured precisely but is not the beads' signal;
#: the knee where the spectrum meets it would read as a dip.
BAND_FLOOR = 1e-4


@dataclass(frozen=True)
class Motion:
    """What :func:`detect_motion` found.

    Attributes
    ----------
    detected : bool
        A straight zero line common to all beads was found.
    length_px : float or None
        Length of the smear, pixels (``1 / t`` of the zero line at ``k.u = t``).
    angle_deg : float or None
        Direction of the smear, degrees from the column axis towards the rows (0: a
        horizontal smear, 90: a vertical one), in [0, 180).
    dip_ratio, dip_z : float
        Depth of the strongest dip: the profile over its flanks' geometric mean, and its
        deficit in standard errors.
    checks : dict
        The dip ratio off the axis (``off_axis``) and in each quarter of the beads
        (``quarters``).
    band_px : float
        Highest frequency (cycles / px) of the band where the signal is seen.
    min_visible_px : float
        Shortest smear whose first zero lies inside that band (``1 / band``): a shorter
        one cannot be told from the optics by this test.
    reason : str
        One sentence for reports.
    """

    detected: bool
    length_px: float | None
    angle_deg: float | None
    dip_ratio: float
    dip_z: float
    checks: dict
    band_px: float
    min_visible_px: float
    reason: str

    def to_dict(self) -> dict:
        """JSON-ready record (a figure that could not be measured is None)."""
        def clean(v):
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple, np.ndarray)):
                return [clean(x) for x in v]
            if isinstance(v, (float, np.floating)):
                return float(v) if np.isfinite(v) else None
            return v.item() if isinstance(v, np.generic) else v
        return clean(asdict(self))


def motion_transfer(fy, fx, length: float, angle_deg: float) -> np.ndarray:
    """Transfer function of a uniform motion of ``length`` px along ``angle_deg``.

    ``sinc(L (f_y sin a + f_x cos a))`` (numpy's ``sinc(x) = sin(pi x) / (pi x)``), with
    frequencies in cycles / px; 1 at zero frequency (the flux is kept).
    """
    a = np.deg2rad(angle_deg)
    return np.sinc(float(length) * (np.asarray(fy) * np.sin(a) + np.asarray(fx) * np.cos(a)))


def _spectra(psf: np.ndarray, n: int) -> np.ndarray:
    k, p, _ = psf.shape
    big = np.zeros((k, n, n))
    big[:, :p, :p] = psf  # the phase does not matter: only powers are used
    return np.abs(sfft.fft2(big, axes=(1, 2))) ** 2


def _mean_power(power: np.ndarray, noise: np.ndarray) -> np.ndarray:
    w = 1.0 / np.maximum(noise, 1e-300)
    return np.einsum("k,kij->ij", w, power - noise[:, None, None]) / w.sum()


def _profile(values, t, s, inside, edges, s_lo, s_hi):
    """Mean of ``values`` over cells of ``t`` (bins ``edges``) with ``s_lo <= |s| < s_hi``
    inside the band, shape (bins,)."""
    sel = inside & (np.abs(s) >= s_lo) & (np.abs(s) < s_hi)
    idx = np.digitize(t[sel], edges) - 1
    ok = (idx >= 0) & (idx < len(edges) - 1)
    tot = np.bincount(idx[ok], weights=values[sel][ok], minlength=len(edges) - 1)
    cnt = np.bincount(idx[ok], minlength=len(edges) - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return tot / cnt, cnt


def _dips(prof, var, cnt, centres, band):
    """Ratio and z of each bin against its flanks at a third of its frequency."""
    ratio = np.full(len(prof), np.inf)
    z = np.zeros(len(prof))
    step = centres[1] - centres[0]
    for j, t0 in enumerate(centres):
        d = max(t0 / 3.0, 2 * step)
        lo, hi = t0 - d, min(t0 + d, band)
        if lo <= step or hi - t0 < step or cnt[j] == 0:
            continue
        jl, jh = int(round((lo - centres[0]) / step)), int(round((hi - centres[0]) / step))
        if jh >= len(prof) or cnt[jl] == 0 or cnt[jh] == 0:
            continue
        a, b = prof[jl], prof[jh]
        # both flanks must stand clear of the noise, or a noisy bin reads as a zero
        if not (a > MIN_DIP_Z * np.sqrt(max(var[jl], 0.0))
                and b > MIN_DIP_Z * np.sqrt(max(var[jh], 0.0)) and a > 0 and b > 0):
            continue
        ref = np.sqrt(a * b)
        ratio[j] = max(prof[j], 0.0) / ref
        z[j] = (ref - prof[j]) / np.sqrt(max(var[j], 1e-300))
    return ratio, z


def detect_motion(
    psf: np.ndarray,
    noise_sd: np.ndarray,
    window: np.ndarray,
    *,
    positions: np.ndarray | None = None,
) -> Motion:
    """Look for a straight zero line common to all beads in their mean power spectrum.

    Parameters
    ----------
    psf : ndarray of shape (K, P, P)
        Sum-1 windowed bead patches (background removed); with fewer than
        :data:`MIN_BEADS` nothing is tested.
    noise_sd : ndarray of shape (K,)
        Per-pixel noise of each patch (image noise / the bead's flux).
    window : ndarray of shape (P, P)
        The window the patches were multiplied by.
    positions : ndarray of shape (K, 2), optional
        Bead positions: the dip must hold in each quarter of the field's beads (by
        position); default: in each quarter of the list.

    Returns
    -------
    Motion
    """
    psf = np.asarray(psf, dtype=np.float64)
    k, p, _ = psf.shape
    sd = np.asarray(noise_sd, dtype=np.float64).reshape(k)
    noise = sd**2 * float((window**2).sum())
    if k < MIN_BEADS:
        return Motion(False, None, None, 1.0, 0.0, {}, float("nan"), float("nan"),
                      f"motion blur not tested: {k} beads (at least {MIN_BEADS} are needed "
                      "to tell a zero line from the noise)")
    n = sfft.next_fast_len(max(4 * p, 64))  # fine bins: a zero line is narrow
    power = _spectra(psf, n)
    f = sfft.fftfreq(n)
    fy, fx = f[:, None] * np.ones((1, n)), np.ones((n, 1)) * f[None, :]
    rad = np.hypot(fy, fx)
    s_all = _mean_power(power, noise)
    # standard error of the mean power, from two halves of the beads
    half = np.arange(k) % 2 == 0
    diff = _mean_power(power[half], noise[half]) - _mean_power(power[~half], noise[~half])
    ring = np.round(rad * n).astype(int)
    ring_var = (np.bincount(ring.ravel(), weights=(diff**2 / 4).ravel())
                / np.maximum(np.bincount(ring.ravel()), 1))
    ring_mean = np.bincount(ring.ravel(), weights=s_all.ravel()) / np.maximum(
        np.bincount(ring.ravel()), 1)
    seen = ((ring_mean > BAND_Z * np.sqrt(ring_var / np.maximum(np.bincount(ring.ravel()), 1)))
            & (ring_mean > BAND_FLOOR * ring_mean[0]))
    seen[0] = True
    last = int(np.argmin(seen)) - 1 if not seen.all() else len(seen) - 1
    band = max(last, 1) / n
    var_map = ring_var[ring]
    inside = rad <= band
    min_visible = 1.0 / band
    none = Motion(False, None, None, 1.0, 0.0, {}, float(band), float(min_visible),
                  f"no straight zero line in the beads' spectrum: no motion blur of "
                  f"{min_visible:.2g} px or more (a shorter one cannot be told from the "
                  f"optics, whose signal reaches {band:.3g} cycles/px here)")
    if band < 3.0 / n:
        return Motion(False, None, None, 1.0, 0.0, {}, float(band), float(min_visible),
                      f"motion blur not tested: {k} beads, signal up to {band:.3g} "
                      "cycles/px")
    edges = (np.arange(int(np.ceil(band * n)) + 2) - 0.5) / n
    centres = 0.5 * (edges[1:] + edges[:-1])
    width = band / 3.0
    angles = np.arange(0.0, 180.0, ANGLE_STEP)
    geometry = []
    for ang in angles:
        a = np.deg2rad(ang)
        geometry.append((np.abs(fy * np.sin(a) + fx * np.cos(a)), -fy * np.cos(a) + fx * np.sin(a)))

    def profiles(spec):
        """Strip profile along every direction, over the mean of all directions: a lens's
        fall towards its cutoff and the knee at the band's edge cancel; a smear's zero
        line does not (shape (angles, bins))."""
        prof = np.array([_profile(spec, t, s_, inside, edges, 0.0, width)[0]
                         for t, s_ in geometry])
        finite = np.isfinite(prof)
        ref = np.where(finite, prof, 0.0).sum(axis=0) / np.maximum(finite.sum(axis=0), 1)
        ref[~finite.any(axis=0)] = np.nan
        with np.errstate(invalid="ignore", divide="ignore"):
            return prof / ref, ref

    rel, ref = profiles(s_all)
    cnt = _profile(np.ones_like(s_all), *geometry[0], inside, edges, 0.0, width)[1]
    pv = np.array([_profile(var_map, t, s_, inside, edges, 0.0, width)[0]
                   for t, s_ in geometry])
    best = (np.inf, 0.0, None, None, None)
    for i, ang in enumerate(angles):
        with np.errstate(invalid="ignore", divide="ignore"):
            var = pv[i] / np.maximum(cnt, 1) / ref**2
        ratio, z = _dips(rel[i], var, cnt, centres, band)
        ok = z >= MIN_DIP_Z
        if ok.any():
            j = int(np.flatnonzero(ok)[np.argmin(ratio[ok])])
            if ratio[j] < best[0]:
                # the zero itself: the deepest bin within the dip's reach (near the band's
                # edge the flanks cannot be tested at the zero, only just before it)
                reach = np.abs(centres - centres[j]) <= centres[j] / 3.0
                vals = np.where(reach & np.isfinite(rel[i]), rel[i], np.inf)
                jz = int(np.argmin(vals))
                best = (float(ratio[j]), float(z[j]), float(ang), float(centres[jz]),
                        float(centres[j]))
    ratio, z, ang, t0, t_dip = best
    if ang is None or ratio > MAX_DIP_RATIO:
        return Motion(False, None, None, float(min(ratio, 1.0)), float(z), {}, float(band),
                      float(min_visible), none.reason)
    # the zero is along one direction only (a ring, from defocus, dips along all of
    # them) and common to every quarter of the beads
    j = int(np.argmin(np.abs(centres - t_dip)))  # where the flanks were tested
    i0 = int(np.argmin(np.abs(angles - ang)))
    across = angles.size // 2
    perp = _dips(rel[(i0 + across) % angles.size], np.zeros(len(centres)), cnt, centres,
                 band)[0][j]
    if positions is not None:
        pos = np.asarray(positions, dtype=np.float64).reshape(k, 2)
        my, mx = np.median(pos, axis=0)
        group = (pos[:, 0] > my).astype(int) * 2 + (pos[:, 1] > mx).astype(int)
    else:
        group = np.arange(k) * 4 // k
    quarters = []
    for g in range(4):
        if np.count_nonzero(group == g) >= 2:
            rq = profiles(_mean_power(power[group == g], noise[group == g]))[0][i0]
            quarters.append(float(_dips(rq, np.zeros(len(centres)), cnt, centres, band)[0][j]))
    checks = {"across": float(perp), "quarters": quarters}
    straight = np.isfinite(perp) and perp > MAX_CHECK_RATIO
    common = all(np.isfinite(q) and q <= MAX_CHECK_RATIO for q in quarters)
    if not (straight and common):
        why = (f"the spectrum dips across it too (ratio {perp:.2f}): a ring, not a line"
               if not straight else "it is not common to all beads (quarters: "
               + ", ".join(f"{q:.2f}" for q in quarters) + ")")
        return Motion(False, None, None, ratio, z, checks, float(band), float(min_visible),
                      f"a dip in the beads' spectrum at {t0:.3g} cycles/px, {ang:.0f} deg, "
                      f"but {why}: not motion blur")
    length = 1.0 / t0  # to a bin, 1 / n cycles/px (n >= 64): ~2 % at 3 px
    return Motion(True, float(length), float(ang), ratio, z, checks, float(band),
                  float(min_visible),
                  f"motion blur: every bead is smeared by {length:.2g} px along "
                  f"{ang:.0f} deg from the columns (a straight zero line in their spectrum at "
                  f"{t0:.3g} cycles/px, {ratio:.2f} of its flanks, z = {z:.0f}); no lens makes "
                  "it. The model includes it, right for this exposure; if the sample was "
                  "still, remove it (remove_motion) or image the beads again")


def remove_motion(stack: np.ndarray, length: float, angle_deg: float, *,
                  reference: np.ndarray | None = None, noise: np.ndarray | None = None
                  ) -> tuple[np.ndarray, dict]:
    """Divide a smear of ``length`` px along ``angle_deg`` out of PSF images.

    Where the reference stands above its noise the gain is ``1 / T`` (capped at
    :data:`~napari_psfspace.core.sphere.MAX_GAIN`); near the smear's zero lines, and
    where there is noise alone, the images are left as they are: what the smear removed
    there is not restored.

    Parameters
    ----------
    stack : ndarray of shape (I, P, P)
        PSF images (e.g. a basis), centred.
    length, angle_deg : float
        As found by :func:`detect_motion`.
    reference, noise : ndarray of shape (P, P), optional
        As in :func:`~napari_psfspace.core.sphere.remove_sphere`.

    Returns
    -------
    out : ndarray of shape (I, P, P)
    info : dict
        JSON-ready: ``length_px``, ``angle_deg``, ``band_px``, ``max_gain_applied``.
    """
    from .sphere import divide_transfer

    out, band, gain = divide_transfer(
        stack, lambda fy, fx: motion_transfer(fy, fx, length, angle_deg), float(length),
        reference=reference, noise=noise)
    return out, {"length_px": float(length), "angle_deg": float(angle_deg),
                 "band_px": band, "max_gain_applied": gain,
                 "method": "the smear's transfer sinc(L k.u) divided out where the beads' "
                           "signal stands above the noise (Wiener-type, capped)"}
