"""The bead rule: how far a usable bead keeps from the image's edge and from other beads,
and the scale at which it is centred, all from the PSF radius ``r`` (pixels).

Every stage that picks or re-checks beads (detection, the estimate, the family's
patches, the diagnosis, the review) uses these, so that a bead usable in one is usable
in all.
"""

from __future__ import annotations

import numpy as np


def bead_border(psf_radius: float) -> float:
    """Least distance (pixels) from a usable bead's centre to the image's edge:
    ``ceil(1.2 r) + 2`` (its windowed patch, a little wider than ``r``, and the pixels its
    sub-pixel centring moves it by). A patch reaching past the edge can be extracted
    (:func:`~napari_psfspace.core.beads.patches.extract_patches` masks the part beyond it),
    but the loop's measured sets read such beads differently,
    so the rule stays until that is understood."""
    return float(np.ceil(1.2 * psf_radius) + 2)


def partial_border(psf_radius: float) -> float:
    """Least distance (pixels) from the centre of a bead used with a partial patch to the
    image's edge: ``r``, so that its PSF lies in the image and only the window's tail
    (background, masked) reaches past the edge. Used for the beads a user clicks to
    identify an operator (a few beads, each worth keeping)."""
    return float(psf_radius)


def min_separation(psf_radius: float) -> float:
    """Least distance (pixels) between two usable beads: ``2 r`` (their PSFs do not
    overlap)."""
    return 2.0 * float(psf_radius)


def centring_sigma(psf_radius: float) -> float:
    """Scale (pixels) of the Gaussian a bead is detected and centred at: ``max(1, r / 4)``
    (the core of a PSF of radius ``r``)."""
    return max(1.0, float(psf_radius) / 4.0)


__all__ = ["bead_border", "centring_sigma", "min_separation", "partial_border"]
