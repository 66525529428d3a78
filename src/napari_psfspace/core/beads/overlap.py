"""How much of a bead's patch its neighbours' light fills: the neighbour rule by energy.

The paper (Appendix A) rejects a bead closer than ``2 r`` to another, whatever their
brightness and shapes; in a crowded field that drops most beads, while a faint bead
``1.8 r`` away adds a percent of the patch's energy, less than its noise. Here a bead is
crowded when its neighbours together add at least :data:`NEIGHBOUR_SHARE` of the energy
in its patch (the disk of radius ``1.2 r``): for each other detection, its core flux
over the bead's times the share of a PSF's energy that falls in a disk whose centre lies
``d`` away, over the share in the disk about its own centre.

The PSF's radial profile is the image's own: the median, over the brightest detections,
of their background-free radial profiles out to ``r`` (the median: a neighbour stands on
one side of a few of them only; the background: the ring beyond ``2 r``).

A kept bead's neighbours within ``2 r`` still add some light: :func:`neighbour_light`
models it (the profile times each one's flux), and
:func:`~napari_psfspace.core.beads.patches.extract_patches` takes it out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .centering import gather_windows

#: A bead whose neighbours add at least this share of the energy in its patch (disk of
#: radius ``1.2 r``) is crowded: the definition of an isolated bead.
NEIGHBOUR_SHARE = 0.05
#: Radius of the patch whose energy is shared, in PSF radii (the window's ``r_ext``).
PATCH_FACTOR = 1.2
#: The windows the profile is measured in reach this many PSF radii; the ring beyond
#: ``2 r`` gives each one's background level.
PROFILE_FACTOR = 2.2
#: At most this many detections (the brightest) give the profile.
PROFILE_BEADS = 64
#: Only neighbours closer than this many PSF radii have their light taken out of a
#: patch: their light reaches the bead's own support. Farther ones reach only the ring
#: the background is fitted on, where the isotropic model's error costs about what it
#: removes.
SUBTRACT_DISTANCE = 2.0


def radial_profile(image: np.ndarray, positions: np.ndarray, psf_radius: float, *,
                   amplitude: np.ndarray | None = None) -> np.ndarray:
    """The median background-free radial profile of the brightest detections.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    positions : ndarray of shape (K, 2)
        Detections (row, column), pixels.
    psf_radius : float
        PSF radius ``r`` in pixels.
    amplitude : ndarray of shape (K,), optional
        Peak amplitudes; the :data:`PROFILE_BEADS` brightest finite ones are used.

    Returns
    -------
    ndarray of shape (floor(r) + 2,)
        Mean intensity in unit-wide rings (ring ``k``: distances in ``[k - 0.5, k +
        0.5)``) of a PSF of unit energy within ``1.2 r``, never negative; zeros when
        there is no detection. Beyond ``r`` the PSF is lost in the noise (the radius's
        definition): what a crowded field's outer rings hold is others' light.
    """
    r = float(psf_radius)
    half = int(np.ceil(PROFILE_FACTOR * r))
    keep = int(np.floor(r)) + 1
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    out = np.zeros(keep + 1)
    if len(pos) == 0:
        return out
    if amplitude is not None:
        a = np.where(np.isfinite(amplitude), amplitude, -np.inf)
        pos = pos[np.argsort(-a, kind="stable")[:PROFILE_BEADS]]
    else:
        pos = pos[:PROFILE_BEADS]
    win = gather_windows(np.asarray(image, np.float64), pos, half)
    d = np.arange(-half, half + 1)
    rho = np.hypot(d[:, None], d[None, :])
    ring = np.rint(rho).astype(int)
    outer = rho > 2.0 * r
    bg = (np.median(win[:, outer], axis=1) if outer.any()
          else np.median(win.reshape(len(pos), -1), axis=1))
    sig = win - bg[:, None, None]
    count = np.bincount(ring.ravel(), minlength=ring.max() + 1)[: half + 1]
    prof = np.stack([np.bincount(ring.ravel(), weights=s.ravel(),
                                 minlength=ring.max() + 1)[: half + 1] for s in sig])
    inside = np.arange(half + 1) <= PATCH_FACTOR * r
    energy = prof[:, inside].sum(axis=1)
    prof = prof / np.maximum(count, 1)
    good = energy > 0
    if not good.any():
        return out
    prof = np.median(prof[good] / energy[good, None], axis=0)
    out[:keep] = np.clip(prof[:keep], 0.0, None)  # and a dark ring: it falls to 0 there
    return out


def disk_shares(profile: np.ndarray, psf_radius: float) -> np.ndarray:
    """Share of a PSF's energy in the patch disk (radius ``1.2 r``) whose centre lies
    ``d`` pixels from the PSF's, over the share when ``d = 0``, for ``d = 0, 1, ...``.

    Parameters
    ----------
    profile : ndarray of shape (L,)
        Radial profile (:func:`radial_profile`), ring ``k`` at ``k`` pixels.
    psf_radius : float

    Returns
    -------
    ndarray of shape (ceil(1.2 r) + L + 1,)
        ``E(d) / E(0)``, 1 at ``d = 0`` and 0 beyond the reach ``1.2 r + L``; zeros when
        the profile holds no light inside the disk.
    """
    r_ext = PATCH_FACTOR * float(psf_radius)
    reach = len(profile) - 1
    n = int(np.ceil(r_ext)) + reach + 1
    d = np.arange(-n, n + 1)
    rho = np.hypot(d[:, None], d[None, :])
    psf = np.interp(rho, np.arange(len(profile)), profile, right=0.0)
    out = np.zeros(n + 1)
    yy = d[:, None] ** 2
    for k in range(n + 1):
        out[k] = psf[yy + (d[None, :] - k) ** 2 <= r_ext ** 2].sum()
    if out[0] <= 0:
        return np.zeros_like(out)
    return out / out[0]


def neighbour_shares(positions: np.ndarray, amplitude: np.ndarray, which: np.ndarray,
                     counted: np.ndarray, shares: np.ndarray, *,
                     neighbour_ratio: float = 0.0) -> np.ndarray:
    """The share of each bead's patch energy that its neighbours add, shape (len(which),).

    Parameters
    ----------
    positions : ndarray of shape (K, 2)
    amplitude : ndarray of shape (K,)
        Brightness (core fluxes, :func:`core_flux`); a non-finite one counts as bright as
        the bead it neighbours; a bead of non-positive brightness is crowded by any
        neighbour in reach (share ``inf``).
    which : ndarray of int
        The beads judged.
    counted : ndarray of int
        The detections that spoil a patch (all but background structure).
    shares : ndarray
        :func:`disk_shares`.
    neighbour_ratio : float
        A detection fainter than this fraction of the bead does not count.
    """
    from scipy.spatial import cKDTree

    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    out = np.zeros(len(which))
    if len(counted) < 2 or len(which) == 0 or not np.any(shares[1:] > 0):
        return out
    reach = float(np.flatnonzero(shares > 0).max() + 1)
    tree = cKDTree(pos[counted])
    amp = np.asarray(amplitude, np.float64)
    grid = np.arange(len(shares))
    for j, (i, found) in enumerate(zip(which, tree.query_ball_point(pos[which], reach),
                                       strict=True)):
        near = counted[np.asarray(found, dtype=np.intp)]
        near = near[near != i]
        if len(near) == 0:
            continue
        dist = np.hypot(*(pos[near] - pos[i]).T)
        e = np.interp(dist, grid, shares, right=0.0)
        a_i = amp[i]
        if not (np.isfinite(a_i) and a_i > 0):
            out[j] = np.inf if np.any(e > 0) else 0.0
            continue
        ratio = np.where(np.isfinite(amp[near]), amp[near] / a_i, 1.0)
        if neighbour_ratio > 0:
            ratio = np.where(ratio < neighbour_ratio, 0.0, ratio)
        out[j] = float(np.sum(np.clip(ratio, 0.0, None) * e))
    return out


def core_flux(image: np.ndarray, positions: np.ndarray, psf_radius: float) -> np.ndarray:
    """Light in each detection's core over its surroundings, shape (K,): the sum over
    the pixels within ``max(1.5, r / 3)`` of it, less their number times the median of the
    window's edge (``r`` away). A flux, not one pixel's peak: a single pixel of a faint
    bead carries its whole Poisson noise, and two PSFs of one flux but different widths
    have different peaks."""
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    if len(pos) == 0:
        return np.zeros(0)
    half = max(2, int(np.ceil(psf_radius)))
    win = gather_windows(np.asarray(image, np.float64), pos, half)
    edge = np.concatenate([win[:, 0, :], win[:, -1, :], win[:, 1:-1, 0], win[:, 1:-1, -1]],
                          axis=1)
    d = np.arange(-half, half + 1)
    core = np.hypot(d[:, None], d[None, :]) <= max(1.5, psf_radius / 3.0)
    return win[:, core].sum(axis=1) - core.sum() * np.median(edge, axis=1)


def patch_shares(image: np.ndarray, positions: np.ndarray, which: np.ndarray,
                 counted: np.ndarray, psf_radius: float, *,
                 neighbour_ratio: float = 0.0) -> np.ndarray | None:
    """:func:`neighbour_shares` measured on ``image``: the PSF's profile from the counted
    detections, each one's brightness its :func:`core_flux`. None when the image shows
    no light there to measure a profile on (the caller falls back to a fixed distance)."""
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    flux = np.full(len(pos), np.nan)
    flux[counted] = core_flux(image, pos[counted], psf_radius)
    rest = np.setdiff1d(which, counted)  # judged but not counted (each bead once)
    flux[rest] = core_flux(image, pos[rest], psf_radius)
    profile = radial_profile(image, pos[counted], psf_radius, amplitude=flux[counted])
    shares = disk_shares(profile, psf_radius)
    if not np.any(shares > 0):
        return None
    return neighbour_shares(pos, flux, which, counted, shares, neighbour_ratio=neighbour_ratio)


@dataclass
class NeighbourLight:
    """A model of the detections' light: each an isotropic PSF (the image's median
    radial profile) times its flux, so that a patch can have its neighbours' light taken
    out before its background is fitted (:func:`~napari_psfspace.core.beads.patches.
    extract_patches`).

    Attributes
    ----------
    positions : ndarray of shape (N, 2)
        The detections (row, column), pixels.
    flux : ndarray of shape (N,)
        Each one's light within ``1.2 r``, image units (0: not modelled).
    profile : ndarray of shape (L,)
        :func:`radial_profile`: unit light within ``1.2 r``, ring ``k`` at ``k`` pixels.
    max_distance : float or None
        Only the detections closer than this to a patch's centre are modelled (pixels;
        None: all whose light reaches the patch).
    """

    positions: np.ndarray
    flux: np.ndarray
    profile: np.ndarray
    max_distance: float | None = None  # only detections closer than this (pixels)

    def around(self, center: np.ndarray, points: np.ndarray) -> np.ndarray:
        """The light at ``points`` (M, 2) of the detections near ``center`` but not at it
        (within 1.5 px: the bead itself), shape (M,)."""
        reach = len(self.profile) - 1
        extent = float(np.max(np.hypot(*(points - center).T))) if len(points) else 0.0
        if self.max_distance is not None:
            extent = min(extent, self.max_distance - reach)
        d = np.hypot(*(self.positions - center).T)
        near = np.flatnonzero((d > 1.5) & (d < reach + extent) & (self.flux > 0))
        out = np.zeros(len(points))
        grid = np.arange(len(self.profile))
        for n in near:
            rho = np.hypot(*(points - self.positions[n]).T)
            out += self.flux[n] * np.interp(rho, grid, self.profile, right=0.0)
        return out


def neighbour_light(image: np.ndarray, positions: np.ndarray, psf_radius: float
                    ) -> NeighbourLight:
    """The :class:`NeighbourLight` of the given detections, measured on ``image``: the
    profile of the brightest, each one's light its :func:`core_flux` over the share of
    the profile's light in the core; those within :data:`SUBTRACT_DISTANCE` radii."""
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    flux = core_flux(image, pos, psf_radius)
    profile = radial_profile(image, pos, psf_radius, amplitude=flux)
    half = max(2, int(np.ceil(psf_radius)))
    d = np.arange(-half, half + 1)
    rho = np.hypot(d[:, None], d[None, :])
    core = rho <= max(1.5, psf_radius / 3.0)
    share = float(np.interp(rho[core], np.arange(len(profile)), profile, right=0.0).sum())
    total = np.where(np.isfinite(flux) & (flux > 0), flux / share, 0.0) if share > 0 \
        else np.zeros(len(pos))
    return NeighbourLight(pos, total, profile, SUBTRACT_DISTANCE * float(psf_radius))


__all__ = ["NEIGHBOUR_SHARE", "NeighbourLight", "core_flux", "disk_shares", "neighbour_light",
           "neighbour_shares", "patch_shares", "radial_profile"]
