"""Neighbours' light taken out with the model's own PSFs, in a crowded field.

A patch cut beside another bead holds some of that bead's light.
:func:`~napari_psfspace.core.beads.overlap.neighbour_light` models it with one isotropic
profile for the whole image. Where the PSF changes over the field (a defocus gradient
puts a wide halo on one side), that profile is wrong near the beads whose light spills
most. Once a first model is fitted, :class:`ModelLight` gives each neighbour the
model's PSF at its own position, at its sub-pixel offset, times its light; the patches
are cut again with it and the model fitted again.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from ..beads.detect import STRUCTURE
from ..beads.overlap import neighbour_light
from ..common.progress import check_halt


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


def model_light(patches, image: np.ndarray, beads, psf_radius: float) -> ModelLight:
    """The :class:`ModelLight` of ``beads`` (all but background structure) on ``image``:
    each one's light as :func:`~napari_psfspace.core.beads.overlap.neighbour_light`
    measures it, its shape the PSF at its position of a first model learnt from
    ``patches`` (the basis by the rank rule, every bead kept: the neighbours' light is a
    small share of a patch, and this model only has to draw it)."""
    from .patch_fit import fit_patches

    first = fit_patches(patches, image.shape, n_psf="rule", z_threshold=np.inf)[1]
    pos = beads.positions[beads.status != STRUCTURE]
    return ModelLight(first, pos, neighbour_light(image, pos, psf_radius).flux)


def crowded(kept: np.ndarray, positions: np.ndarray, size: int) -> bool:
    """Whether a kept bead has another detection within a patch's width (``size``
    pixels): then one's light reaches the other's patch or its background ring."""
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    if len(pos) < 2 or len(kept) == 0:
        return False
    dist, _ = cKDTree(pos).query(pos[kept], k=2)
    return bool(np.any(dist[:, 1] < size))


__all__ = ["ModelLight", "crowded", "model_light"]
