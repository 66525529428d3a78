"""Neighbours' light taken out with the model's own PSFs, in a crowded field.

A patch cut beside another bead holds some of that bead's light.
:func:`~napari_psfspace.core.beads.overlap.neighbour_light` models it with one isotropic
profile for the whole image. Where the PSF changes over the field (a defocus gradient
puts a wide halo on one side), that profile is wrong near the beads whose light spills
most. Once a first model is fitted, :class:`ModelLight` gives each neighbour the
model's PSF at its own position, at its sub-pixel offset, times its light; the patches
are cut again with it and the model fitted again.

Each detection's light is fitted to the image with the model's PSF at its position
(:func:`fit_light`), not read from its core with the isotropic profile: in a defocus
gradient the profile holds too much light in a wide PSF's core, and the defocused beads'
light came out a third short. :func:`deblend` repeats the three steps (a model from the
patches, the light fitted with it, the patches cut again) until the light settles
(:data:`DEBLEND_TOL`, at most :data:`DEBLEND_PASSES` times): each pass's patches are
cleaner, so the next model draws the neighbours better.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from ..beads.detect import STRUCTURE
from ..beads.overlap import neighbour_light
from ..common.progress import check_halt

#: Most passes of :func:`deblend` (a model, the light fitted with it, the patches cut
#: again).
DEBLEND_PASSES = 6
#: :func:`deblend` stops once a pass changes the detections' light by less than this
#: (relative, 90th percentile): a neighbour adds a fraction of a patch's light, so the
#: patches then move by less than a percent of their neighbours' light. Each pass
#: about halves the change.
DEBLEND_TOL = 0.01
#: Passes of :func:`fit_light` over the detections (Gauss-Seidel: each fit uses the
#: neighbours' latest light).
LIGHT_PASSES = 3


class ModelLight:
    """The detections' light as the model's PSFs: the interface of
    :class:`~napari_psfspace.core.beads.overlap.NeighbourLight` (``around``).

    Parameters
    ----------
    operator : ProductConvolution
        The model (its ``psf_at`` gives a sum-1 PSF of ``psf_size`` pixels).
    positions : ndarray of shape (N, 2)
        The detections (row, column), pixels.
    flux : ndarray of shape (N,)
        Each one's light (image units; 0: not modelled), e.g. ``NeighbourLight.flux``.
    """

    def __init__(self, operator, positions: np.ndarray, flux: np.ndarray):
        self.operator = operator
        self.positions = np.asarray(positions, np.float64).reshape(-1, 2)
        self.flux = np.asarray(flux, np.float64).reshape(-1)
        self.reach = operator.psf_size / 2.0 + 1.0
        self._psfs: dict[int, np.ndarray] = {}

    def _psf(self, n: int) -> np.ndarray:
        if n not in self._psfs:
            self._psfs[n] = self.operator.psf_at(*self.positions[n])
        return self._psfs[n]

    def around(self, center: np.ndarray, points: np.ndarray) -> np.ndarray:
        """The light at ``points`` (M, 2) of the detections near ``center`` but not at it
        (within 1.5 px: the bead itself), shape (M,): each detection's PSF re-sampled
        (cubic spline) at the points' offsets from it."""
        points = np.asarray(points, np.float64).reshape(-1, 2)
        extent = float(np.max(np.hypot(*(points - center).T))) if len(points) else 0.0
        d = np.hypot(*(self.positions - center).T)
        near = np.flatnonzero((d > 1.5) & (d < self.reach + extent) & (self.flux > 0))
        out = np.zeros(len(points))
        for n in near:
            check_halt()
            h = self._psf(n)
            rel = points - self.positions[n] + h.shape[0] // 2
            out += self.flux[n] * ndi.map_coordinates(h, rel.T, order=3, mode="constant",
                                                      cval=0.0)
        return out


def fit_light(light: ModelLight, image: np.ndarray, psf_radius: float, *,
              passes: int = LIGHT_PASSES) -> ModelLight:
    """Each detection's light fitted to ``image``, in place (``light.flux``).

    For each detection, the image over the disk of radius ``r`` about it, less its
    neighbours' modelled light, is fitted by least squares with its own model PSF times a
    light plus a constant (the local background); a negative light is 0. Each fit uses
    the neighbours' latest light (Gauss-Seidel, ``passes`` sweeps): with overlapping
    PSFs, holding them all at the last sweep's (Jacobi) overshoots and oscillates. The
    light is that of the model's PSF, sum 1 over the patch's window.
    """
    img = np.asarray(image, np.float64)
    half = int(np.ceil(psf_radius))
    d = np.arange(-half, half + 1)
    dy, dx = (a[np.hypot(*np.meshgrid(d, d, indexing="ij")) <= psf_radius]
              for a in np.meshgrid(d, d, indexing="ij"))
    light.flux = np.array(light.flux, np.float64)
    for _ in range(passes):
        for n, p in enumerate(light.positions):
            check_halt()
            ys, xs = np.rint(p[0]).astype(int) + dy, np.rint(p[1]).astype(int) + dx
            inside = (ys >= 0) & (ys < img.shape[0]) & (xs >= 0) & (xs < img.shape[1])
            pts = np.stack([ys[inside], xs[inside]], axis=1).astype(np.float64)
            h = light._psf(n)
            a = np.stack([ndi.map_coordinates(h, (pts - p + h.shape[0] // 2).T, order=3,
                                              mode="constant", cval=0.0),
                          np.ones(len(pts))], axis=1)
            y = img[ys[inside], xs[inside]] - light.around(p, pts)
            light.flux[n] = max(float(np.linalg.lstsq(a, y, rcond=None)[0][0]), 0.0)
    return light


def model_light(patches, image: np.ndarray, beads, psf_radius: float,
                light: ModelLight | None = None) -> ModelLight:
    """The :class:`ModelLight` of ``beads`` (all but background structure) on ``image``:
    each one's shape the PSF at its position of a model learnt from ``patches`` (the
    basis by the rank rule, every bead kept: the neighbours' light is a small share of a
    patch, and this model only has to draw it), its light fitted with it
    (:func:`fit_light`), starting from ``light``'s or, without one, from what
    :func:`~napari_psfspace.core.beads.overlap.neighbour_light` measures."""
    from .patch_fit import fit_patches

    model = fit_patches(patches, image.shape, n_psf="rule", z_threshold=np.inf)[1]
    pos = beads.positions[beads.status != STRUCTURE]
    flux = (light.flux if light is not None and len(light.flux) == len(pos)
            else neighbour_light(image, pos, psf_radius).flux)
    return fit_light(ModelLight(model, pos, flux), image, psf_radius)


def deblend(patches, kept: np.ndarray, image: np.ndarray, beads, psf_radius: float, cut, *,
            passes: int = DEBLEND_PASSES, tol: float = DEBLEND_TOL):
    """The patches of a crowded field, cut with the neighbours' light taken out.

    Up to ``passes`` times: a model from the last patches with the detections' light
    fitted with it (:func:`model_light`); then ``cut(light, kept)``, the caller's cut of
    the beads ``kept`` (the last cut's: a bead left out once stays out, as its status
    says), gives the next ``(kept, patches)``: ``kept`` the indices into ``beads`` of the
    patches (None patches when a cut leaves none). It stops once a
    pass changes the light by less than ``tol`` (:func:`light_change`). Returns the last
    cut's ``(kept, patches)``.
    """
    light = None
    for _ in range(passes):
        last, light = light, model_light(patches, image, beads, psf_radius, light)
        kept, patches = cut(light, kept)
        if patches is None or (last is not None and light_change(last, light) < tol):
            break  # no usable patch left, or the light has settled
    return kept, patches


def light_change(before: ModelLight, after: ModelLight) -> float:
    """The 90th percentile of the relative change of the detections' light between two
    passes, over those with at least a tenth of the median light (fainter ones barely
    reach a patch)."""
    a, b = np.asarray(before.flux, np.float64), np.asarray(after.flux, np.float64)
    if a.shape != b.shape or not len(b):
        return np.inf
    use = b > 0.1 * np.median(b)
    if not use.any():
        return 0.0
    return float(np.percentile(np.abs(b[use] - a[use]) / b[use], 90))


def crowded(kept: np.ndarray, positions: np.ndarray, size: int) -> bool:
    """Whether a kept bead has another detection within a patch's width (``size``
    pixels): then one's light reaches the other's patch or its background ring."""
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    if len(pos) < 2 or len(kept) == 0:
        return False
    dist, _ = cKDTree(pos).query(pos[kept], k=2)
    return bool(np.any(dist[:, 1] < size))


__all__ = ["DEBLEND_PASSES", "DEBLEND_TOL", "ModelLight", "crowded", "deblend", "fit_light",
           "light_change", "model_light"]
