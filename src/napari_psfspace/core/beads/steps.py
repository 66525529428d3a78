"""Generator forms of the bead steps a panel runs on its own: detection and the radius
suggestion.

Each is one call that cannot yield, so it runs in a helper thread while the generator
yields a record every fraction of a second (:func:`..common.progress.wait_with_progress`):
a consumer that stops between two records (a panel's Cancel) is answered at once, and the
call's result is dropped.
"""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from ..common.progress import Progress, wait_with_progress
from .detect import Beads, detect_beads
from .radius import suggest_psf_radius
from .slice_radius import SliceRadius, suggest_slice_radius


def iter_detect_beads(image: np.ndarray, psf_radius: float, *, threshold: float = 8.0
                      ) -> Generator[Progress, None, Beads]:
    """Generator form of :func:`.detect.detect_beads`: yields progress while it runs,
    returns the :class:`.detect.Beads`.

    Parameters
    ----------
    image : (M, N) array
        The bead image.
    psf_radius : float
        PSF radius in pixels.
    threshold : float
        Detection threshold in noise standard deviations.
    """
    return (yield from wait_with_progress(
        lambda: detect_beads(image, psf_radius, threshold=threshold),
        Progress("detect", 0.1, "detecting beads...")))


def iter_suggest_psf_radius(image: np.ndarray) -> Generator[Progress, None, float]:
    """Generator form of :func:`.radius.suggest_psf_radius`: yields progress while it
    runs, returns the radius in pixels.

    Parameters
    ----------
    image : (M, N) array
        The bead image.
    """
    return (yield from wait_with_progress(
        lambda: suggest_psf_radius(image),
        Progress("suggest", 0.1, "measuring the widths of bright spots...")))


def iter_suggest_slice_radius(stack, index: int) -> Generator[Progress, None, SliceRadius]:
    """Generator form of :func:`.slice_radius.suggest_slice_radius`: the radius of one
    slice of a stack from it and its neighbours; yields progress while it runs."""
    return (yield from wait_with_progress(
        lambda: suggest_slice_radius(stack, index),
        Progress("suggest", 0.1, f"measuring the widths of bright spots on slice {index} "
                                 "and its neighbours...")))
