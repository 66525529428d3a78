"""Best focus of a bead z-stack: the slice where the beads are sharpest.

Raw contrast (the standard deviation of a slice) prefers a defocused ring at high NA: a
ring spreads the same photons over more bright pixels. So does the light within a disk
sized by the PSF radius: a ring of a few pixels falls inside a disk of ``r / 4`` when
``r`` is 20. What focus does is raise each bead's peak: :func:`bead_peaks` is each
bead's peak in each slice (the brightest 3 x 3 mean within 1.5 pixels of its centre,
above the median of a ring about it, the same whatever the radius), and the best focus
is the slice of the highest median of the beads' peaks, each bead scaled to its own
highest (:func:`focus_measure`), so that a few bright beads do not decide alone.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from ..common.errors import NoBeadsError, PsfSpaceError
from ..common.validate import as_stack
from .detect import detect_beads
from .radius import suggest_psf_radius

#: A bead's peak is its brightest 3 x 3 mean within this many pixels of its centre.
PEAK_REACH = 1.5
#: Detections whose highest peak is below this share of the bright beads' (the 90th
#: percentile) do not vote: ring fragments, dust.
MIN_PEAK_SHARE = 0.3


def _stack(stack) -> np.ndarray:
    return np.asarray(as_stack(stack, min_side=8))


def bead_peaks(stack, centers, psf_radius: float) -> np.ndarray:
    """Each bead's peak on each slice, above its local background.

    Parameters
    ----------
    stack : ndarray of shape (Z, M, N)
    centers : array_like of shape (K, 2)
        The beads' lateral centres (row, column), pixels.
    psf_radius : float
        The PSF radius in focus, pixels: the background is the median of the ring from
        ``1.5 r`` to ``2 r`` about each bead (clipped at the slice's edges).

    Returns
    -------
    ndarray of shape (K, Z), float64
        The brightest 3 x 3 mean within :data:`PEAK_REACH` pixels of each centre, less
        the ring's median.
    """
    arr = np.asarray(stack)
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    z, h, w = arr.shape
    outer = int(np.ceil(2 * float(psf_radius)))
    out = np.zeros((len(centers), z))
    for k, (cy, cx) in enumerate(centers):
        y, x = int(round(cy)), int(round(cx))
        y0, y1, x0, x1 = max(y - outer, 0), min(y + outer + 1, h), max(x - outer, 0), \
            min(x + outer + 1, w)
        if y1 - y0 < 3 or x1 - x0 < 3:
            continue
        win = arr[:, y0:y1, x0:x1].astype(np.float64)
        yy, xx = np.ogrid[y0 - cy:y1 - cy, x0 - cx:x1 - cx]
        d2 = yy * yy + xx * xx
        ring = (d2 > (1.5 * psf_radius) ** 2) & (d2 <= (2 * psf_radius) ** 2)
        near = d2 <= PEAK_REACH ** 2
        if not near.any():
            near = d2 <= d2.min()
        sm = ndi.uniform_filter(win, size=(1, 3, 3), mode="nearest")
        bg = np.median(win[:, ring], axis=1) if ring.any() else np.median(
            win.reshape(z, -1), axis=1)
        out[k] = sm[:, near].max(axis=1) - bg
    return out


def focus_measure(stack, *, psf_radius: float | None = None, n_beads: int = 60
                  ) -> np.ndarray:
    """How sharp the beads are in each slice, shape (Z,).

    Parameters
    ----------
    stack : array_like of shape (Z, M, N)
        A bead z-stack (the same field at each focus).
    psf_radius : float, optional
        The PSF radius in focus, pixels; default suggested from the maximum projection.
        It sets the background ring only: the measure does not grow with it.
    n_beads : int
        At most this many beads (the brightest on the projection, away from its border).

    Returns
    -------
    ndarray of shape (Z,), float64
        The median over the beads of each bead's peak (:func:`bead_peaks`) over its
        highest, in [0, 1] (negative peaks count as 0), over the beads whose highest
        peak reaches :data:`MIN_PEAK_SHARE` of the bright beads'.

    Raises
    ------
    PsfSpaceError
        No bead is found on the maximum projection (then there is no focus to measure).
    """
    arr = _stack(stack)
    proj = arr.max(axis=0)
    if float(proj.max()) == float(proj.min()):
        raise PsfSpaceError("`stack` is constant: there is no focus to measure.")
    r = float(psf_radius) if psf_radius else suggest_psf_radius(proj, wings=1.0)
    beads = detect_beads(proj, r)
    _, h, w = arr.shape
    edge = int(np.ceil(PEAK_REACH)) + 2
    keep = np.all((beads.positions >= edge) & (beads.positions <= np.array([h, w]) - edge - 1),
                  axis=1)
    if not keep.any():
        raise PsfSpaceError(f"No bead lies {edge} px or more from the border of the maximum "
                            "projection: the focus cannot be measured.")
    order = np.argsort(-beads.amplitude[keep], kind="stable")[:n_beads]
    peaks = np.clip(bead_peaks(arr, beads.positions[keep][order], r), 0.0, None)
    top = peaks.max(axis=1)
    # a detection on a defocused ring (a radius too small for the rings splits them on
    # the projection) peaks at a few % of a bead in focus: only beads whose highest peak
    # reaches MIN_PEAK_SHARE of the bright beads' vote
    bright = top >= MIN_PEAK_SHARE * np.percentile(top, 90) if len(top) else top > 0
    bright &= top > 0
    peaks = peaks[bright] / top[bright, None]
    if len(peaks) == 0:
        raise PsfSpaceError("No bead stands above its background on any slice: the focus "
                            "cannot be measured.")
    return np.median(peaks, axis=0)


def best_focus_index(stack, *, psf_radius: float | None = None) -> int:
    """Index of the slice in focus: the sharpest beads (:func:`focus_measure`).

    Falls back to the slice of highest contrast (standard deviation) when no bead can be
    measured on the stack's maximum projection.
    """
    arr = _stack(stack)
    try:
        return int(np.argmax(focus_measure(arr, psf_radius=psf_radius)))
    except (NoBeadsError, PsfSpaceError):
        return int(np.argmax(arr.reshape(arr.shape[0], -1).astype(np.float32).std(axis=1)))


#: A slice's suggested radius beyond this factor of the in-focus slice's is explained.
SLICE_RATIO = 1.5


def radius_against_focus(stack, index: int, radius: float, *, focus: int | None = None,
                         focus_radius: float | None = None) -> str:
    """Why a slice's radius departs from the in-focus slice's by more than
    :data:`SLICE_RATIO`, in one sentence; empty when it does not (or is the focus).

    Parameters
    ----------
    stack : ndarray of shape (Z, M, N)
    index : int
        The slice the radius is for.
    radius : float
        Its suggested radius, pixels.
    focus, focus_radius : optional
        The best-focus slice and its suggested radius, where already known.
    """
    arr = np.asarray(stack)
    focus = best_focus_index(arr) if focus is None else int(focus)
    if focus == index:
        return ""
    try:
        r_focus = suggest_psf_radius(arr[focus]) if focus_radius is None else focus_radius
    except PsfSpaceError:
        return ""
    ratio = float(radius) / r_focus
    if 1 / SLICE_RATIO <= ratio <= SLICE_RATIO:
        return ""

    def count(image, r):
        try:
            b = detect_beads(image, r)
            return int(np.count_nonzero(b.kept)), len(b)
        except PsfSpaceError:
            return 0, 0

    kept, found = count(arr[index], radius)
    kept_f, found_f = count(arr[focus], r_focus)
    return (f"slice {index} is {abs(index - focus)} slice(s) from the best focus (slice "
            f"{focus}, radius {r_focus:g} px, {kept_f} of {found_f} beads kept): its "
            f"beads are {'wider' if ratio > 1 else 'narrower'} there, {ratio:.2f}x "
            f"({radius:g} px, {kept} of {found} beads kept); pass --psf-radius to choose "
            "another.")


__all__ = ["MIN_PEAK_SHARE", "PEAK_REACH", "SLICE_RATIO", "bead_peaks", "best_focus_index",
           "focus_measure", "radius_against_focus"]
