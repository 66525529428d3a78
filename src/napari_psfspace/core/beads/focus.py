"""Best focus of a bead z-stack: the slice where the beads concentrate their light.

Raw contrast (the standard deviation of a slice) prefers a defocused ring at high NA: a
ring spreads the same photons over more bright pixels. What focus does is concentrate
each bead's energy: :func:`focus_measure` is, per slice, the share of the beads' light
(above each bead's local background) that falls within a small disk about their centres,
summed over the beads found on the stack's maximum projection.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from ..common.errors import PsfSpaceError

#: Slices whose beads keep less than this share of the most light any slice keeps within
#: ``2 r`` of their centres are out of focus (their measure is 0).
MIN_LIGHT_SHARE = 0.25


def _stack(stack) -> np.ndarray:
    arr = np.asarray(stack)
    if arr.ndim != 3:
        raise ValueError(f"`stack` must be 3-D (Z, Y, X), got shape {arr.shape}.")
    if arr.shape[0] < 1 or min(arr.shape[1:]) < 8:
        raise ValueError(f"`stack` must hold slices of at least 8 x 8 pixels, got shape "
                         f"{arr.shape}.")
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"`stack` must be a real array, got dtype {arr.dtype}.")
    return arr


def focus_measure(stack, *, psf_radius: float | None = None, n_beads: int = 60
                  ) -> np.ndarray:
    """How concentrated the beads' light is in each slice, shape (Z,).

    Parameters
    ----------
    stack : array_like of shape (Z, M, N)
        A bead z-stack (the same field at each focus).
    psf_radius : float, optional
        The PSF radius in focus, pixels; default suggested from the maximum projection.
    n_beads : int
        At most this many beads (the brightest on the projection, away from its border).

    Returns
    -------
    ndarray of shape (Z,), float64
        For each slice, the beads' light within ``max(1.5, r / 4)`` pixels of their
        centres over their light within ``2 r`` (each above the median of the ring just
        outside, per bead and slice), pooled over the beads. Slices that keep less than
        :data:`MIN_LIGHT_SHARE` of the most light any slice keeps within ``2 r`` get 0.

    Raises
    ------
    PsfSpaceError
        No bead is found on the maximum projection (then there is no focus to measure).
    """
    from .detect import detect_beads
    from .scale import suggest_psf_radius

    arr = _stack(stack)
    proj = arr.max(axis=0)
    if float(proj.max()) == float(proj.min()):
        raise PsfSpaceError("`stack` is constant: there is no focus to measure.")
    # the spots' visible radius: the focus is measured on isolated beads' cores
    r = float(psf_radius) if psf_radius else suggest_psf_radius(proj, wings=1.0)
    beads = detect_beads(proj, r)
    z, h, w = arr.shape
    outer = int(np.ceil(2 * r))
    keep = np.all((beads.positions >= outer + 2)
                  & (beads.positions <= np.array([h, w]) - outer - 3), axis=1)
    pos = np.rint(beads.positions[keep]).astype(int)
    if len(pos) == 0:
        raise PsfSpaceError(f"No bead lies {outer + 2} px or more from the border of the "
                            f"maximum projection: the focus cannot be measured with a PSF "
                            f"radius of {r:g} px.")
    pos = pos[np.argsort(-beads.amplitude[keep], kind="stable")][:n_beads]
    yy, xx = np.mgrid[-outer - 2:outer + 3, -outer - 2:outer + 3]
    dist = np.hypot(yy, xx)
    core = dist <= max(1.5, r / 4)
    inside = dist <= outer
    ring = dist > outer
    num = np.zeros(z)
    den = np.zeros(z)
    for y, x in pos:
        win = arr[:, y - outer - 2:y + outer + 3, x - outer - 2:x + outer + 3].astype(np.float64)
        win = ndi.uniform_filter(win, size=(1, 3, 3))  # the core's noise, a little
        bg = np.median(win[:, ring], axis=1)
        num += (win[:, core] - bg[:, None]).sum(axis=1)
        den += (win[:, inside] - bg[:, None]).sum(axis=1)
    # a slice whose beads keep little of their light within 2 r is far from focus; its
    # ratio of two small, noisy sums means nothing
    valid = den >= MIN_LIGHT_SHARE * den.max() if den.max() > 0 else np.zeros(z, bool)
    return np.where(valid, np.clip(num, 0, None) / np.where(valid, den, 1), 0.0)


def best_focus_index(stack, *, psf_radius: float | None = None) -> int:
    """Index of the slice in focus: the most concentrated beads (:func:`focus_measure`).

    Falls back to the slice of highest contrast (standard deviation) when no bead can be
    measured on the stack's maximum projection.
    """
    from .detect import NoBeadsError

    arr = _stack(stack)
    try:
        return int(np.argmax(focus_measure(arr, psf_radius=psf_radius)))
    except (NoBeadsError, PsfSpaceError):
        return int(np.argmax(arr.reshape(arr.shape[0], -1).astype(np.float32).std(axis=1)))


__all__ = ["best_focus_index", "focus_measure"]
