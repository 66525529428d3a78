"""Motion blur of a calibration image: find it, report it, and remove it on request.

A stage or sample that moves by ``L`` pixels along a direction ``u`` during the exposure
convolves every bead with the same line segment. Its transfer function is
``sinc(L k.u)`` (:func:`motion_transfer`): it vanishes on the straight lines
``k.u = +-1/L, +-2/L, ...`` of the Fourier plane. A rotationally symmetric lens makes
no such zeros: its transfer falls smoothly to its cutoff, and the zeros that strong
defocus or spherical aberration bring are rings, not straight lines. :func:`detect_motion`
looks for one straight zero line, common to all beads, inside the band where the beads'
mean signal stands above its noise, and, where the zero lies too near the optics' cutoff
to be bracketed, for the smear's ``sinc^2`` fall below it (:data:`MAX_EDGE_RATIO`). It
reports the smear's length and direction, or says that no motion long enough to be seen
is there (a smear whose first zero lies beyond that band cannot be told from the optics:
:attr:`Motion.min_visible_px`).

**One thing a single image cannot tell from a smear**: the line focus of an astigmatic
lens (a cylindrical lens for 3-D localisation, or astigmatism with about as much
defocus). In geometric optics a line focus *is* a uniform segment, with the same
straight zero lines; on simulated beads with 0.1-0.3 waves rms of uniform astigmatism
and 0.5-1.5 times as much defocus, the test reads a line in 29 of 52 scenes
(motion). The record says so. A z-stack tells them apart: a smear
keeps its length and direction through focus, a line focus shrinks and turns by 90
degrees on the other side of the best focus.

Motion blurs a sample imaged the same way just as much, so the learnt operator is right
*for that exposure*; a calibration meant for other exposures should remove it
(``remove_motion=True``, :func:`remove_motion`) once the user knows the sample was still
while imaging, or image the beads again.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import fft as sfft

from .denoise import patch_noise
from .motion_fit import fit_line, refine_line
from .motion_spectrum import BeadSpectrum

#: Fewest beads tested: two halves estimate the noise and four quarters must agree (with
#: 10-12 beads of low signal, a quarter of 2-3 beads read a zero by chance: 1 false
#: alarm in 97 effect-free scenes of the family, none from 16 beads up).
MIN_BEADS = 16
#: Directions tried, degrees (0: along the columns, 90: along the rows).
ANGLE_STEP = 2.0
#: A dip is a zero line when the profile there is below this fraction of the geometric
#: mean of its two flanks (a sinc's zero with flanks at a third of the way to the
#: neighbouring lobes: < 0.05 without noise) ...
MAX_DIP_RATIO = 0.3
#: ... by at least this many standard errors of the profile there,
MIN_DIP_Z = 6.0
#: ... while the perpendicular direction shows no dip below this ratio there (a line, not
#: a ring); every quarter of the beads must show the same line (MAX_QUARTER_RATIO).
MAX_CHECK_RATIO = 0.5
#: Every quarter of the beads must show its own dip, at most this deep a ratio, within
#: QUARTER_ANGLE degrees and QUARTER_FREQUENCY (relative) of the zero line found in all
#: of them: the same line, whatever depth the field's aberrations give it there.
MAX_QUARTER_RATIO = 0.7
QUARTER_ANGLE = 4.0
QUARTER_FREQUENCY = 0.15
#: What every detection says besides the smear (see the module's docstring).
ALTERNATIVE = ("Motion during the exposure, or the line focus of an astigmatic lens "
               "(astigmatism with about as much defocus, or a cylindrical lens), which one "
               "image cannot tell apart: in a z-stack a smear keeps its direction through "
               "focus, a line focus turns by 90 degrees. The model includes it, right for "
               "this exposure; if it is motion and the sample was still, remove it "
               "(remove_motion) or image the beads again")
#: A smear whose zero lies near the optics' cutoff: its second lobe (a few % of the
#: first, on an optical transfer that is nearly gone there) sinks into the spectrum's
#: floor, so the zero has no upper flank and reads as a cutoff, not a dip
#: (``bench/bench_motion.py``). Below its zero, though, the power along the smear
#: still falls, against the perpendicular direction, as ``sinc^2(L t)``, to a ratio no
#: lens reaches: this route reports a smear when that ratio (plus two standard errors)
#: falls below MAX_EDGE_RATIO (97 effect-free scenes of the family reach >= 0.07, 3-px
#: smears 0.003-0.03) ...
MAX_EDGE_RATIO = 0.03
#: ... the ratio's logarithm follows ``log sinc^2(L t)`` below the zero within this RMS
#: (smears 0.1-0.25; still scenes fit no smear: the best length is the shortest tried),
#: the zero ``1 / L`` lies near where the ratio is lowest (0.9-1.3 times that frequency),
#: and every quarter of the beads shows the ratio below MAX_CHECK_RATIO there.
MAX_EDGE_RMS = 0.3


@dataclass(frozen=True)
class Motion:
    """What :func:`detect_motion` found.

    Attributes
    ----------
    detected : bool
        A straight zero line common to all beads was found.
    length_px : float or None
        Length of the smear, pixels: ``1 / t`` of the zero line at ``k.u = t``, refined
        by the ``sinc^2`` fitted near it
        (:func:`~napari_psfspace.core.model.motion_fit.fit_line`; the line's own bin is
        ``checks["length_grid_px"]``).
    angle_deg : float or None
        Direction of the smear, degrees from the column axis towards the rows (0: a
        horizontal smear, 90: a vertical one), in [0, 180); refined the same way (the
        lowest line's direction is ``checks["angle_line_deg"]``).
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


def _dips(prof, var, cnt, centres, band):
    """Ratio and z of each bin against its flanks at a third of its frequency."""
    nb = len(prof)
    ratio = np.full(nb, np.inf)
    z = np.zeros(nb)
    step = centres[1] - centres[0]
    d = np.maximum(centres / 3.0, 2 * step)
    lo, hi = centres - d, np.minimum(centres + d, band)
    jl = np.rint((lo - centres[0]) / step).astype(int)
    jh = np.rint((hi - centres[0]) / step).astype(int)
    ok = (lo > step) & (hi - centres >= step) & (cnt > 0) & (jh < nb) & (jl >= 0)
    jl, jh = np.where(ok, jl, 0), np.where(ok, np.minimum(jh, nb - 1), 0)
    a, b = prof[jl], prof[jh]
    sd = np.sqrt(np.clip(var, 0.0, None))
    with np.errstate(invalid="ignore"):
        # both flanks must stand clear of the noise, or a noisy bin reads as a zero
        ok &= (cnt[jl] > 0) & (cnt[jh] > 0) & (a > 0) & (b > 0)
        ok &= (a > MIN_DIP_Z * sd[jl]) & (b > MIN_DIP_Z * sd[jh])
    ok &= np.isfinite(prof)
    ref = np.sqrt(np.where(ok, a * b, 1.0))
    ratio[ok] = np.maximum(prof[ok], 0.0) / ref[ok]
    z[ok] = (ref[ok] - prof[ok]) / np.sqrt(np.maximum(var[ok], 1e-300))
    return ratio, z


def _edge_smear(rel, var, centres, band, angles, quarter_rels):
    """The second route of :func:`detect_motion` (see :data:`MAX_EDGE_RATIO`): a smear
    whose zero has no upper flank. ``rel``: profiles along every direction (angles,
    bins), ``var`` their variances, ``quarter_rels()`` the profiles of each quarter of the
    beads (computed only when needed). Returns ``(length, angle, ratio, rms, quarters)``
    or None."""
    na = angles.size
    half = na // 2
    sd = np.sqrt(np.clip(np.nan_to_num(var, nan=np.inf), 0.0, None))
    step = centres[1] - centres[0]
    best = (np.inf, -1, -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        for i in range(na):
            j = (i + half) % na
            a, b = rel[i], rel[j]
            ok = (np.isfinite(a) & np.isfinite(b) & (b > MIN_DIP_Z * sd[j])
                  & (centres > 2 * step) & (centres <= band))
            if not ok.any():
                continue
            r = np.where(ok, (np.maximum(a, 0.0) + 2 * sd[i]) / b, np.inf)
            k = int(np.argmin(r))
            if r[k] < best[0]:
                best = (float(r[k]), i, k)
    r_min, i, k = best
    if not r_min <= MAX_EDGE_RATIO:
        return None
    j = (i + half) % na
    t_min = centres[k]
    a, b = rel[i], rel[j]
    with np.errstate(invalid="ignore", divide="ignore"):
        use = ((centres > step) & (centres <= t_min) & (a > MIN_DIP_Z * sd[i])
               & (b > MIN_DIP_Z * sd[j]))
        log_r = np.log(a / b)
    lengths = np.exp(np.linspace(0.0, np.log(0.5 / step), 600))  # 1 px up, ~0.7 % steps
    fit = (np.inf, None)
    for length in lengths:
        s2 = np.sinc(length * centres) ** 2
        m = use & (length * centres < 1.0) & (s2 > 0.05)
        if np.count_nonzero(m) < 3:
            continue
        rms = float(np.sqrt(np.mean((log_r[m] - np.log(s2[m])) ** 2)))
        if rms < fit[0]:
            fit = (rms, float(length))
    rms, length = fit
    # the shortest length tried fits best: the ratio does not fall as a smear's would
    if length is None or length <= 1.05 * lengths[0] or rms > MAX_EDGE_RMS:
        return None
    if not 0.9 * t_min <= 1.0 / length <= 1.3 * t_min:
        return None
    quarters = []
    with np.errstate(invalid="ignore", divide="ignore"):
        for q in quarter_rels():
            quarters.append(float(max(q[i][k], 0.0) / q[j][k]))
    if not all(np.isfinite(q) and q <= MAX_CHECK_RATIO for q in quarters):
        return None
    return length, float(angles[i]), r_min, rms, quarters


def detect_motion(
    psf: np.ndarray,
    noise_sd: np.ndarray,
    window: np.ndarray,
    *,
    positions: np.ndarray | None = None,
    probe: tuple[float, float] | None = None,
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
    probe : (length_px, angle_deg), optional
        A smear known from elsewhere (a simulation's truth, a stage log): the record's
        ``checks["probe"]`` then says whether this test *could* see it, i.e. whether
        both flanks of its zero line stand clear of the noise inside the band
        (``testable``), and the dip ratio and z measured there. It changes nothing
        else; benches use it to count the scenes where a smear is visible at all (the
        search's own condition, at the true place: some bin within a third of its
        frequency from the zero has both flanks clear).

    Returns
    -------
    Motion
    """
    psf = np.asarray(psf, dtype=np.float64)
    k, p, _ = psf.shape
    sd = np.asarray(noise_sd, dtype=np.float64).reshape(k)
    noise = patch_noise(sd, window)
    if k < MIN_BEADS:
        return Motion(False, None, None, 1.0, 0.0, {}, float("nan"), float("nan"),
                      f"not tested: {k} beads (at least {MIN_BEADS} are needed "
                      "to tell a zero line from the noise)")
    n = sfft.next_fast_len(max(4 * p, 64))  # fine bins: a zero line is narrow
    spec = BeadSpectrum(psf, noise, _quarters(positions, k), n)
    band, min_visible = spec.band, 1.0 / spec.band
    if band < 3.0 / n:
        return Motion(False, None, None, 1.0, 0.0, {}, float(band), float(min_visible),
                      f"not tested: the beads' signal reaches only {band:.3g} "
                      "cycles/px")
    angles = np.arange(0.0, 180.0, ANGLE_STEP)
    spec.set_strips(angles, band / 3.0)
    rel, ref = spec.profiles(spec.mean)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = spec.strip_profiles(spec.var_map) / np.maximum(spec.counts, 1) / ref**2
    probed = {} if probe is None else {"probe": _probe_record(spec, rel, var, angles, probe)}
    ratio, z, ang, t0, t_dip = _deepest_dip(spec, rel, var, angles)
    if ang is None or ratio > MAX_DIP_RATIO:
        return _edge_or_none(spec, rel, var, angles, probed, ratio, z)
    checks, why = _line_checks(spec, rel, angles, ang, t0, t_dip, probed)
    if why:
        return Motion(False, None, None, ratio, z, checks, float(band), float(min_visible),
                      f"a dip in the beads' spectrum at {t0:.3g} cycles/px, {ang:.0f} deg, "
                      f"but {why}: not motion blur")
    # the direction to a tenth of a degree (the line's lowest frequency is not the
    # length: it moved off the truth on smears whose zero the aberrations shift), then
    # the length from the sinc^2 over the whole band
    ang_line = refine_line(spec.mean, spec.ring_mean, n, ang, t0, band / 3.0, band)[0]
    ang, length = fit_line(spec.mean, spec.var_map, n, ang_line, t0, band)
    checks.update(length_grid_px=float(1.0 / t0), angle_line_deg=float(ang_line))
    return Motion(True, float(length), float(ang), ratio, z, checks, float(band),
                  float(min_visible),
                  f"every bead is smeared by {length:.2g} px along "
                  f"{ang:.0f} deg from the columns (a straight zero line in their spectrum at "
                  f"{t0:.3g} cycles/px, {ratio:.2f} of its flanks, z = {z:.0f}). "
                  + ALTERNATIVE)


def _quarters(positions, k: int) -> np.ndarray:
    """Each bead's quarter of the field, 0-3, by position (default: of the list)."""
    if positions is None:
        return np.arange(k) * 4 // k
    pos = np.asarray(positions, dtype=np.float64).reshape(k, 2)
    my, mx = np.median(pos, axis=0)
    return (pos[:, 0] > my).astype(int) * 2 + (pos[:, 1] > mx).astype(int)


def _probe_record(spec: BeadSpectrum, rel, var, angles, probe) -> dict:
    """Whether the search could see a smear known from elsewhere (``probe`` of
    :func:`detect_motion`), and the dip's ratio and z at its place."""
    centres, band = spec.centres, spec.band
    plen, pang = float(probe[0]), float(probe[1]) % 180.0
    ip = int(np.argmin(np.minimum(np.abs(angles - pang), 180 - np.abs(angles - pang))))
    pr, pz = _dips(rel[ip], var[ip], spec.counts, centres, band)
    t_p = 1.0 / plen
    # as the search reads it: a bin whose flanks are clear and whose reach (a third of
    # its frequency) holds the zero
    near = np.isfinite(pr) & (np.abs(centres - t_p) <= centres / 3.0)
    ok_p = bool(t_p < band and near.any())
    jp = int(np.flatnonzero(near)[np.argmin(pr[near])]) if ok_p else 0
    return {"testable": ok_p, "ratio": float(pr[jp]) if ok_p else None,
            "z": float(pz[jp]) if ok_p else None}


def _deepest_dip(spec: BeadSpectrum, rel, var, angles) -> tuple:
    """The deepest significant dip over every direction: its ratio to its flanks, its z,
    direction, the zero's frequency (the deepest bin within the dip's reach: near the
    band's edge the flanks cannot be tested at the zero, only just before it) and the
    frequency where its flanks were tested; ``(inf, 0, None, None, None)`` for none."""
    centres = spec.centres
    best = (np.inf, 0.0, None, None, None)
    for i, ang in enumerate(angles):
        ratio, z = _dips(rel[i], var[i], spec.counts, centres, spec.band)
        ok = z >= MIN_DIP_Z
        if ok.any():
            j = int(np.flatnonzero(ok)[np.argmin(ratio[ok])])
            if ratio[j] < best[0]:
                reach = np.abs(centres - centres[j]) <= centres[j] / 3.0
                vals = np.where(reach & np.isfinite(rel[i]), rel[i], np.inf)
                jz = int(np.argmin(vals))
                best = (float(ratio[j]), float(z[j]), float(ang), float(centres[jz]),
                        float(centres[j]))
    return best


def _edge_or_none(spec: BeadSpectrum, rel, var, angles, probed, ratio, z) -> Motion:
    """No zero line: a smear whose zero lies too near the cutoff to be bracketed
    (:func:`_edge_smear`), or no motion blur."""
    band, min_visible = spec.band, 1.0 / spec.band
    edge = _edge_smear(rel, var, spec.centres, band, angles,
                       lambda: [spec.quarter_profiles(g) for g in range(4)
                                if np.count_nonzero(spec.group == g) >= 2])
    if edge is None:
        return Motion(False, None, None, float(min(ratio, 1.0)), float(z), probed,
                      float(band), float(min_visible),
                      f"no straight zero line in the beads' spectrum: no motion blur of "
                      f"{min_visible:.2g} px or more (a shorter one cannot be told from the "
                      f"optics, whose signal reaches {band:.3g} cycles/px here)")
    length, e_ang, e_ratio, e_rms, quarters = edge
    return Motion(True, length, e_ang, e_ratio, float("nan"),
                  {"route": "edge", "fit_rms": e_rms, "quarters": quarters, **probed},
                  float(band), float(min_visible),
                  f"every bead is smeared by {length:.2g} px along {e_ang:.0f} deg "
                  f"from the columns: along it the beads' power falls, against the "
                  f"perpendicular direction, as the smear's sinc^2 to "
                  f"{e_ratio:.3f} near its zero at {1 / length:.3g} cycles/px (the "
                  "zero itself lies too near the optics' cutoff to be bracketed). "
                  + ALTERNATIVE)


def _line_checks(spec: BeadSpectrum, rel, angles, ang, t0, t_dip, probed) -> tuple[dict, str]:
    """The checks that a dip is a smear's zero line: along one direction only (a ring,
    from defocus, dips along all of them), and common to every quarter of the beads;
    returns the checks and why the dip is not a line ("" where it is)."""
    centres, cnt, band = spec.centres, spec.counts, spec.band
    j = int(np.argmin(np.abs(centres - t_dip)))  # where the flanks were tested
    i0 = int(np.argmin(np.abs(angles - ang)))
    across = angles.size // 2
    perp = _dips(rel[(i0 + across) % angles.size], np.zeros(len(centres)), cnt, centres,
                 band)[0][j]
    # common to every quarter: its own deepest dip near the same direction and frequency
    # (within QUARTER_ANGLE degrees and QUARTER_FREQUENCY of it). Its depth is not asked
    # to match: field-varying aberrations change how deep a smear's zero reads from one
    # part of the field to another, not where it lies
    near_angles = [(i0 + d) % angles.size
                   for d in range(-int(QUARTER_ANGLE // ANGLE_STEP),
                                  int(QUARTER_ANGLE // ANGLE_STEP) + 1)]
    near_bins = np.flatnonzero(np.abs(centres - t0) <= max(QUARTER_FREQUENCY * t0,
                                                          1.01 * (centres[1] - centres[0])))
    quarters, places = [], []
    for g in range(4):
        if np.count_nonzero(spec.group == g) >= 2:
            rq = spec.quarter_profiles(g)
            best_q = (np.inf, None)
            for ia in near_angles:
                rr = _dips(rq[ia], np.zeros(len(centres)), cnt, centres, band)[0]
                jj = near_bins[np.argmin(rr[near_bins])] if len(near_bins) else j
                if rr[jj] < best_q[0]:
                    best_q = (float(rr[jj]), (float(angles[ia]), float(centres[jj])))
            quarters.append(best_q[0])
            places.append(best_q[1])
    checks = {"across": float(perp), "quarters": quarters,
              "quarter_places": [p_ for p_ in places if p_ is not None], **probed}
    straight = np.isfinite(perp) and perp > MAX_CHECK_RATIO
    common = all(np.isfinite(q) and q <= MAX_QUARTER_RATIO for q in quarters)
    if straight and common:
        return checks, ""
    return checks, (f"the spectrum dips across it too (ratio {perp:.2f}): a ring, not a "
                    "line" if not straight else "it is not common to all beads (quarters: "
                    + ", ".join(f"{q:.2f}" for q in quarters) + ")")


def remove_motion(stack: np.ndarray, length: float, angle_deg: float, *,
                  reference: np.ndarray | None = None, noise: np.ndarray | None = None
                  ) -> tuple[np.ndarray, dict]:
    """Divide a smear of ``length`` px along ``angle_deg`` out of PSF images.

    Where the reference's smeared signal stands above its noise the gain is ``1 / T``;
    near the smear's zero lines, and where there is noise alone, the images are left as
    they are: what the smear removed there is not restored. Between the two the cap is
    set by the signal (``max_gain=None`` of
    :func:`~napari_psfspace.core.beads.sphere.divide_transfer`), not a fixed number.

    Parameters
    ----------
    stack : ndarray of shape (I, P, P)
        PSF images (e.g. a basis), centred.
    length, angle_deg : float
        As found by :func:`detect_motion`.
    reference, noise : ndarray of shape (P, P), optional
        As in :func:`~napari_psfspace.core.beads.sphere.remove_sphere`.

    Returns
    -------
    out : ndarray of shape (I, P, P)
    info : dict
        JSON-ready: ``length_px``, ``angle_deg``, ``band_px``, ``max_gain_applied``.
    """
    from ..beads.sphere import divide_transfer

    out, band, gain = divide_transfer(
        stack, lambda fy, fx: motion_transfer(fy, fx, length, angle_deg), float(length),
        reference=reference, noise=noise, max_gain=None)
    return out, {"length_px": float(length), "angle_deg": float(angle_deg),
                 "band_px": band, "max_gain_applied": gain,
                 "method": "the smear's transfer sinc(L k.u) divided out where the beads' "
                           "signal stands above the noise (Wiener-type, the cap set "
                           "by the signal)"}
