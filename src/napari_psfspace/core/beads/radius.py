"""The PSF radius of a model learnt from an image's beads, suggested from the image.

* :func:`suggest_psf_radius` measures, around spots found at their own scale
  (:func:`~.scale.spot_scale`), the radius that encloses most of their energy within the
  signal's extent, on each spot's own pixels (those nearer it than any other spot: a
  neighbour is not its halo), above a plane fitted to its surroundings (a gradient is not
  a halo either), within :data:`SEARCH_SCALES` scales of it.
* :func:`suggest_series_radius`: one radius for a series of images (the slices of a
  stack, the conditions of a family): measured on the middle image first, then outwards.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from ..common.errors import NoBeadsError, PsfSpaceError
from ..common.validate import check_int, check_positive
from .detect import detect_beads
from .scale import prepare_image, reusing, spot_scale

#: :func:`suggest_psf_radius` looks this many spot scales around each spot (and at least
#: :data:`MIN_SEARCH` pixels): far enough for the wings of a spot in focus, near enough
#: that a slight error of the background does not add up to a halo.
SEARCH_SCALES = 12.0
MIN_SEARCH = 24
#: :func:`suggest_psf_radius`: the model's radius over the spots' visible radius. One
#: bead shows its PSF down to its own noise; the model learns from all the beads at once
#: and still sees the wings below it (rings, the slow tail of an Airy pattern), so a
#: model cut at the visible radius is worse than a wider one. The factor comes from a
#: sweep of the radius on simulated scenes of two optics codes (aberration-free to
#: strong, bright and faint, the error against the true PSF) and on the measured stacks
#: (the held-out error): ``bench/bench_radius_sweep.py``.
WINGS = 1.5
#: A wider radius is suggested only while it keeps this fraction of the beads kept at
#: the visible radius (beads must be isolated at the radius: a dense field loses them).
KEEP_FRACTION = 0.5


def _spot_radius(win: np.ndarray, own: np.ndarray, energy: float) -> int | None:
    """The radius enclosing ``energy`` of a spot's energy within its signal's extent,
    from its azimuthal median profile over its ``own`` pixels, above a plane fitted to
    the outer part of them (None when it cannot be measured)."""
    room = win.shape[0] // 2
    yy, xx = np.mgrid[-room:room + 1, -room:room + 1]
    dist = np.hypot(yy, xx)
    ring = np.rint(dist).astype(int)
    # the background: a plane through the outer part of the spot's own pixels (on one
    # side only where a neighbour is near: a gradient must not read as a halo)
    reach = int(ring[own].max())
    outer = own & (ring >= max(2, int(0.6 * reach)))
    if outer.sum() < 12:
        return None
    design = np.column_stack([np.ones(outer.sum()), yy[outer], xx[outer]])
    vals = win[outer]
    use = np.ones(len(vals), bool)
    for _ in range(2):  # least squares, then without the outliers (a neighbour's wing)
        coef, *_ = np.linalg.lstsq(design[use], vals[use], rcond=None)
        res = vals - design @ coef
        sd = 1.4826 * float(np.median(np.abs(res[use] - np.median(res[use]))))
        trimmed = np.abs(res) <= 3 * sd
        if sd <= 0 or trimmed.sum() < 12:
            break
        use = trimmed
    flat = win - (coef[0] + coef[1] * yy + coef[2] * xx)
    labels = np.where(own & (ring <= room), ring, -1)
    count = np.bincount(labels[labels >= 0], minlength=room + 1)[:room + 1]
    if count[0] == 0:
        return None
    prof = np.full(room + 1, np.nan)  # NaN where fewer than 3 own pixels
    idx = np.union1d(np.flatnonzero(count >= 3), [0])
    prof[idx] = np.asarray(ndi.median(flat, labels=labels, index=idx))
    ring_sd = 1.25 * sd / np.sqrt(np.maximum(count, 1))
    strong = prof >= 3 * ring_sd
    if not strong.any():
        return None
    # the signal's extent: where the profile first falls back to the noise after its
    # first significant ring (a faint ring out of focus has a dark centre: its profile
    # starts in the noise)
    first = int(np.argmax(strong))
    low = np.flatnonzero(~strong[first:])
    extent = first + int(low[0]) if len(low) else room
    if extent < 1:
        return None
    full = 2 * np.pi * np.maximum(np.arange(extent + 1), 0.5)  # a whole ring's pixels
    full[0] = 1.0
    enclosed = np.cumsum(np.clip(prof[:extent + 1], 0, None) * full)
    return int(np.searchsorted(enclosed, energy * enclosed[-1]))


#: Spots whose energy radius exceeds this many times the median spot's do not set the
#: radius (the defocused slices of the measured stacks).
MAX_OVER_MEDIAN = 2.5


def suggest_psf_radius(image, *, n_beads: int = 20, energy: float = 0.97,
                       max_radius: float | None = None, wings: float = WINGS) -> float:
    """Suggest the PSF radius ``r`` (pixels) for a model learnt from an image's spots.

    The spots are found at their own scale ``sigma`` (:func:`spot_scale`), so that a ring
    out of focus is one spot at its centre, not several on its edge. For the strongest few
    in each cell of a 4 x 4 tiling of the field (the PSF varies over the field), the
    azimuthal median profile above the local background (a plane through the outer part
    of the window) gives the enclosed energy, on the pixels nearer that spot than any
    other (so that neighbours do not count as its halo), within
    :data:`SEARCH_SCALES` scales of it; a spot's radius is where the energy reaches
    ``energy`` of the total within the signal's extent (the profile above 3 noise sd of a
    ring median). The radius must bound the widest PSFs of the field, so the 75th
    percentile over the spots, plus one pixel, is the spots' *visible radius*; spots
    wider than :data:`MAX_OVER_MEDIAN` times the median spot (aggregates, dust,
    structure) do not count.

    The model is learnt from all the beads at once and still sees the wings below one
    bead's noise, so the suggestion is ``wings`` times the visible radius
    (:data:`WINGS`), or, where that wider radius would keep fewer than
    :data:`KEEP_FRACTION` of the beads isolated at the visible radius, halfway to it,
    else the visible radius itself.

    Parameters
    ----------
    image : array_like of shape (M, N)
    n_beads : int
        About how many spots are used (spread over the field).
    energy : float
        Enclosed-energy fraction that defines a spot's radius.
    max_radius : float, optional
        Largest radius considered; default ``min(M, N) / 8``.
    wings : float
        The suggestion over the visible radius (1: the visible radius, e.g. to detect
        beads rather than to model them).

    Returns
    -------
    float
        Suggested radius in pixels, at least 3.

    Raises
    ------
    NoBeadsError
        No spot stands out of the noise.
    """
    n_beads = check_int(n_beads, "n_beads", minimum=1)
    if not 0 < check_positive(energy, "energy") < 1:
        raise ValueError(f"`energy` must be a fraction in (0, 1), got {energy!r}.")
    with reusing(image):  # the image prepared, its scales filtered, once for all radii
        return _suggest(image, n_beads, energy, max_radius, wings)


def spot_radii(image, *, n_beads: int = 20, energy: float = 0.97,
               max_radius: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The spots :func:`suggest_psf_radius` measures and their radii.

    Returns
    -------
    positions : ndarray of shape (K, 2)
        Row and column of each spot measured (pixels), aggregates left out.
    radii : ndarray of shape (K,)
        The radius enclosing ``energy`` of each one's light (pixels).

    Raises
    ------
    NoBeadsError
        No spot stands out of the noise, or none could be measured.
    """
    with reusing(image):
        pos, radii, _ = _measure(image, n_beads, energy, max_radius)
    return pos, radii


def _measure(image, n_beads: int, energy: float, max_radius: float | None
             ) -> tuple[np.ndarray, np.ndarray, int]:
    """(positions, radii, largest radius considered) of the spots measured."""
    img, _, _, _ = prepare_image(image)
    h, w = img.shape
    rmax = int(max_radius or max(6, min(h, w) // 8))
    try:
        found = spot_scale(image, max_sigma=max(1.0, rmax / 2.0))
    except NoBeadsError as exc:
        raise NoBeadsError(f"{exc} No `psf_radius` can be suggested: give it yourself if "
                           "the image does hold beads.") from None
    search = int(min(rmax, max(MIN_SEARCH, np.ceil(SEARCH_SCALES * found.sigma))))
    spots = np.rint(found.spots).astype(int)
    # the strongest few in each cell of a 4 x 4 tiling: the whole field counts
    cell = (spots[:, 0] * 4 // h) * 4 + spots[:, 1] * 4 // w
    order = np.lexsort((-found.strength, cell))
    rank = np.arange(len(order)) - np.searchsorted(cell[order], cell[order])
    chosen = order[rank < max(1, n_beads // 16 + 1)]
    tree = cKDTree(found.all_spots) if len(found.all_spots) > 1 else None
    radii, where = [], []
    for y, x in spots[chosen]:
        room = int(min(search, y, x, h - 1 - y, w - 1 - x))
        if room < 4:
            continue
        win = img[y - room:y + room + 1, x - room:x + room + 1].astype(np.float64)
        yy, xx = np.mgrid[-room:room + 1, -room:room + 1]
        own = np.ones(win.shape, bool)
        if tree is not None:  # the pixels nearer this spot than any other
            for j in tree.query_ball_point((y, x), 2 * room + 1):
                dy, dx = found.all_spots[j][0] - y, found.all_spots[j][1] - x
                if dy * dy + dx * dx >= 1.0:
                    own &= yy**2 + xx**2 <= (yy - dy) ** 2 + (xx - dx) ** 2
        r = _spot_radius(win, own, energy)
        if r is not None:
            radii.append(r)
            where.append((y, x))
    if not radii:
        raise NoBeadsError("Could not measure the width of any bright spot: give "
                           "`psf_radius` yourself.")
    radii_a = np.asarray(radii, float)
    # a spot far wider than the median spot is an aggregate, dust or structure, not a
    # bead: on a defocused slice of few beads one such spot set the radius
    keep = radii_a <= MAX_OVER_MEDIAN * np.median(radii_a)
    return np.asarray(where, float)[keep], radii_a[keep], rmax


def _suggest(image, n_beads: int, energy: float, max_radius: float | None,
             wings: float) -> float:
    _, radii, rmax = _measure(image, n_beads, energy, max_radius)
    visible = float(max(3.0, np.ceil(np.percentile(radii, 75)) + 1.0))
    if not wings > 1.0:
        return visible
    return _wider_radius(image, visible, float(wings), rmax)


def _wider_radius(image, visible: float, wings: float, rmax: int) -> float:
    """``wings x visible`` (or halfway to it) where it keeps :data:`KEEP_FRACTION` of
    the beads kept at ``visible``, else ``visible``."""
    def kept(r: float) -> int:
        try:
            return int(np.count_nonzero(detect_beads(image, r).kept))
        except PsfSpaceError:
            return 0

    base = kept(visible)
    for factor in (wings, (1.0 + wings) / 2):
        r = float(min(np.ceil(factor * visible), rmax))
        if r <= visible:
            break
        if base and kept(r) >= KEEP_FRACTION * base:
            return r
    return visible


#: :func:`suggest_series_radius` tries at most this many images.
SERIES_TRIES = 7


def suggest_series_radius(read: Callable[[int], np.ndarray], n_images: int, *,
                          tries: int = SERIES_TRIES) -> tuple[float, int]:
    """One PSF radius for a series of images: :func:`suggest_psf_radius` on the middle
    image, else the next one outwards (a stack's ends are often out of focus or empty,
    where no radius can be measured), at most ``tries`` of them.

    Parameters
    ----------
    read : callable
        ``read(i)``: the ``i``-th image, shape (M, N).
    n_images : int
    tries : int

    Returns
    -------
    radius : float
        Pixels.
    index : int
        The image it was measured on.

    Raises
    ------
    NoBeadsError
        None of the images tried shows a spot standing out of the noise.
    """
    n = check_int(n_images, "n_images", minimum=1)
    for i in sorted(range(n), key=lambda j: abs(j - n // 2))[:int(tries)]:
        try:
            return suggest_psf_radius(read(i)), i
        except ValueError:
            continue
    raise NoBeadsError("no PSF radius could be measured on the middle images (no bright "
                       "spot stands out of the noise)")


__all__ = ["KEEP_FRACTION", "MAX_OVER_MEDIAN", "MIN_SEARCH", "SEARCH_SCALES", "SERIES_TRIES",
           "WINGS", "spot_radii", "suggest_psf_radius", "suggest_series_radius"]
