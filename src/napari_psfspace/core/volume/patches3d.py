"""3D bead patches from a z-stack: every bead seen through focus, on one common plane.

Each bead's patch is cut around its lateral centre (sub-pixel, from the bead plane) on
the same planes for every bead, ``plane - z_radius .. plane + z_radius``. The patches are
not re-centred on each bead's own focus: :meth:`Patches3D.registered` moves each one
only by its bead's distance from the field's focal surface
(:mod:`~napari_psfspace.core.volume.focal_surface`), so that a focus a plane higher
because of field curvature or a tilted slide stays in the patch, and the model keeps it.

Each plane of a patch is cut by the 2D patches' spline re-sampling at the bead's sub-pixel centre,
its background (an order-2 polynomial fitted outside the PSF radius ``r``, plane by
plane: a background that changes with depth is followed) removed and the bump window of
the 2D patches applied. A patch is divided by the bead's flux per plane (the mean of its
three largest plane sums): a plane of the normalised patch sums to about 1, the flux a
plane of a widefield stack receives from a point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..beads.background import fit_background
from ..beads.patches import R_EXT_FACTOR, observed_mask, patch_size, resample_patches
from ..beads.window import bump_window, radial_distance
from .focal_surface import shift_planes


@dataclass
class Patches3D:
    """Background-free, windowed, flux-normalised 3D patches of K beads.

    Attributes
    ----------
    centers : ndarray of shape (K, 2)
        Lateral centres (row, column), pixels.
    psf : ndarray of shape (K, Zp, P, P)
        Normalised patches (a plane sums to about 1).
    flux : ndarray of shape (K,)
        Each bead's flux per plane (image units).
    noise : ndarray of shape (K,)
        Robust sd of its background-free pixels beyond ``r`` (image units).
    planes : ndarray of shape (Zp,), int
        The stack's planes the patches hold (``plane - z_radius`` to ``plane +
        z_radius``; planes beyond the stack are zero).
    r, r_ext : float
        PSF radius and the window's outer radius, pixels.
    inside : ndarray of shape (Zp,), bool, optional
        The planes holding measured light for every bead (default: the planes inside
        the stack); patches moved along z bead by bead hold less.
    """

    centers: np.ndarray
    psf: np.ndarray
    flux: np.ndarray
    noise: np.ndarray
    planes: np.ndarray
    r: float
    r_ext: float
    inside: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.centers)

    @property
    def size(self) -> int:
        return int(self.psf.shape[-1])

    def subset(self, index) -> Patches3D:
        return Patches3D(self.centers[index], self.psf[index], self.flux[index],
                         self.noise[index], self.planes, self.r, self.r_ext, self.inside)

    def data_planes(self, depth: int) -> np.ndarray:
        """The planes holding measured light for every bead, (Zp,) bool, in a stack of
        ``depth`` planes."""
        if self.inside is not None:
            return np.asarray(self.inside, bool)
        return (self.planes >= 0) & (self.planes < int(depth))

    def registered(self, shifts: np.ndarray, margin: int, depth: int) -> Patches3D:
        """The patches moved along z by ``-shifts`` planes (each bead's focus onto the
        focal surface: :func:`~napari_psfspace.core.volume.focal_surface.shift_planes`),
        ``margin`` planes cut from each end (they were cut for the move, at least the
        largest ``|shift|``)."""
        s = np.nan_to_num(np.asarray(shifts, np.float64))
        keep = slice(margin, len(self.planes) - margin)
        psf = shift_planes(self.psf, s)[:, keep]
        planes = self.planes[keep]
        lo, hi = (float(min(s.min(), 0.0)), float(max(s.max(), 0.0))) if len(s) else (0, 0)
        # a plane holds a bead's light where it came from within half a plane of the stack
        inside = (planes + lo >= -0.5) & (planes + hi <= int(depth) - 0.5)
        return Patches3D(self.centers, psf, self.flux, self.noise, planes, self.r,
                         self.r_ext, inside)


def extract_patches_3d(stack: np.ndarray, centers: np.ndarray, psf_radius: float, *,
                       plane: int, z_radius: int) -> Patches3D:
    """Cut, clean and normalise the 3D patches of beads at lateral ``centers``.

    Parameters
    ----------
    stack : ndarray of shape (Z, H, W)
    centers : ndarray of shape (K, 2)
        Sub-pixel lateral centres (row, column), pixels.
    psf_radius : float
        ``r``, pixels: the widest plane's PSF radius (beyond it, background only).
    plane : int
        The bead plane's index.
    z_radius : int
        Planes on each side of ``plane``.

    Returns
    -------
    Patches3D
        A bead whose flux is not positive keeps a zero patch and ``flux <= 0``.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    r = float(psf_radius)
    r_ext = R_EXT_FACTOR * r
    size = patch_size(r)
    planes = np.arange(plane - z_radius, plane + z_radius + 1)
    window = bump_window(size, r, r_ext)
    outside = radial_distance(size) > r
    seen = observed_mask(centers, size, stack.shape[-2:])
    whole = bool(seen.all())
    signal = np.zeros((len(centers), len(planes), size, size))
    resid = []
    for j, z in enumerate(planes):
        if not 0 <= z < stack.shape[0]:
            continue
        raw = resample_patches(np.asarray(stack[z], np.float64), centers, size)
        clean = raw - fit_background(raw, r, observed=None if whole else seen)
        if not whole:  # beyond the image's edge: no light measured
            clean[~seen] = 0.0
        signal[:, j] = clean * window
        resid.append(np.where(seen, clean, np.nan)[:, outside])
    res = np.concatenate(resid, axis=1)
    mid = np.nanmedian(res, axis=1, keepdims=True)
    noise = 1.4826 * np.nanmedian(np.abs(res - mid), axis=1)
    sums = signal.sum(axis=(2, 3))  # (K, Zp)
    top = np.sort(sums, axis=1)[:, -min(3, sums.shape[1]):]
    flux = top.mean(axis=1)
    psf = np.zeros_like(signal)
    good = flux > 0
    psf[good] = signal[good] / flux[good, None, None, None]
    return Patches3D(centers, psf, flux, noise, planes, r, r_ext)


def bead_planes(stack: np.ndarray, centers: np.ndarray, psf_radius: float) -> np.ndarray:
    """Each bead's plane of best focus: where its peak above the local background is
    highest (:func:`~napari_psfspace.core.beads.focus.bead_peaks`; a ring out of focus is
    bright but spread, its centre dark, whatever the PSF radius).

    Returns
    -------
    ndarray of shape (K,), int
    """
    from ..beads.focus import bead_peaks

    return np.argmax(bead_peaks(stack, centers, psf_radius), axis=1)


__all__ = ["Patches3D", "bead_planes", "extract_patches_3d"]
