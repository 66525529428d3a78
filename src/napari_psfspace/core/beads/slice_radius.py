"""The PSF radius of one slice of a stack, following focus from slice to slice.

One slice measured alone can jump: a few wide spots (a bead out of focus, an aggregate
the median test keeps) or a slice with hardly a spot sets its radius, and the next slice
reads half or twice it. :func:`suggest_slice_radius` measures the slice and its two
neighbours (:func:`~.radius.suggest_psf_radius` on each) and uses their median. Where the
slice's own reading departs from a neighbour's by more than :data:`~.focus.SLICE_RATIO`,
it says so and names the spots that set the slice's reading: the widest where it reads
wider, the narrowest where it reads narrower.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..common.errors import NoBeadsError, PsfSpaceError
from ..common.validate import check_int
from .focus import SLICE_RATIO
from .radius import spot_radii, suggest_psf_radius

#: Spots named as setting a slice's reading where it jumps.
DRIVERS = 3


@dataclass
class SliceRadius:
    """Result of :func:`suggest_slice_radius`.

    Attributes
    ----------
    radius : float
        The radius to use for the slice: the median of its own and its neighbours'
        readings (pixels).
    own : float
        The slice's own reading (NaN where none could be measured).
    readings : dict of int to float
        Each slice measured (the slice and its neighbours) and its reading (NaN where
        none could be measured).
    reason : str
        Empty where the slice's reading is within :data:`~.focus.SLICE_RATIO` of each
        neighbour's; else why the radius used is not its own, with the spots that set
        its reading.
    drivers : ndarray of shape (D, 3)
        Row, column and radius (pixels) of the spots named in ``reason``.
    """

    radius: float
    own: float
    readings: dict = field(default_factory=dict)
    reason: str = ""
    drivers: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def _reading(image) -> float:
    try:
        return float(suggest_psf_radius(image))
    except PsfSpaceError:
        return float("nan")


def suggest_slice_radius(stack, index: int) -> SliceRadius:
    """The PSF radius of slice ``index`` of a stack, from it and its two neighbours.

    Parameters
    ----------
    stack : array_like of shape (Z, M, N)
        A z-stack (read slice by slice: a dask or memory-mapped stack stays lazy).
    index : int
        The slice, from 0.

    Returns
    -------
    SliceRadius

    Raises
    ------
    NoBeadsError
        No spot could be measured on the slice or its neighbours.
    """
    depth = int(np.shape(stack)[0])
    index = check_int(index, "index", minimum=0)
    if index >= depth:
        raise ValueError(f"`index` must be a slice of the stack (0 to {depth - 1}), got "
                         f"{index}.")
    slices = [k for k in (index - 1, index, index + 1) if 0 <= k < depth]
    readings = {k: _reading(np.asarray(stack[k])) for k in slices}
    finite = [r for r in readings.values() if np.isfinite(r)]
    if not finite:
        raise NoBeadsError(f"no PSF radius could be measured on slice {index} or its "
                           "neighbours (no bright spot stands out of the noise): give it "
                           "yourself")
    radius = float(np.median(finite))
    own = readings[index]
    if not np.isfinite(own):
        return SliceRadius(radius, own, readings,
                           f"slice {index} shows no spot to measure: the median of its "
                           f"neighbours' readings, {radius:g} px, is used")
    jumps = {k: r for k, r in readings.items()
             if k != index and np.isfinite(r) and max(own / r, r / own) > SLICE_RATIO}
    if not jumps:
        return SliceRadius(radius, own, readings)
    wider = own > np.median(list(jumps.values()))
    try:
        pos, radii = spot_radii(np.asarray(stack[index]))
        order = np.argsort(radii)[::-1] if wider else np.argsort(radii)
        pick = order[:DRIVERS]
        drivers = np.column_stack([pos[pick], radii[pick]])
    except NoBeadsError:
        drivers = np.zeros((0, 3))
    named = ", ".join(f"({y:.0f}, {x:.0f}) {r:.0f} px" for y, x, r in drivers)
    others = " and ".join(f"{r:g} px on slice {k}" for k, r in jumps.items())
    reason = (f"slice {index} alone reads {own:g} px against {others} (more than "
              f"{SLICE_RATIO:g}x): its {'widest' if wider else 'narrowest'} spots set it"
              + (f", at (row, column) {named}" if named else "")
              + f"; the median of the slice and its neighbours, {radius:g} px, is used")
    return SliceRadius(radius, own, readings, reason, drivers)


__all__ = ["DRIVERS", "SliceRadius", "suggest_slice_radius"]
