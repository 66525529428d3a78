"""One image's contribution to a subspace: its beads' patches (step 1 of section 2.4).

The beads stage as the single-image estimate runs it (detection with hot pixels masked,
sub-pixel centring, rejection of beads that moved to the border, windowed background-free
patches), without learning anything: the basis is learnt from the patches of all
images together. Runs as one dask task per image.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..beads.centering import refine_centers
from ..beads.detect import Beads, NoBeadsError, detect_beads, flag_unusable
from ..beads.patches import Patches
from ..common.spacing import bead_border, centring_sigma
from ..common.validate import as_image
from ..model.deblend import crowded, deblend
from ..model.estimate import ESTIMATE_IMAGES, faint_beads, kept_patches
from ..model.fewbeads import FEW_BEADS


@dataclass
class ImagePatches:
    """The usable beads of one image of a stack.

    Attributes
    ----------
    index : int
        Position of the image in the stack.
    shape : (int, int)
        Image shape, pixels.
    patches : Patches or None
        Windowed, background-free, sum-1 patches of the kept beads (None: none usable).
    summary : str
        The bead table's summary (what was kept and why the others were not).
    """

    index: int
    shape: tuple[int, int]
    patches: Patches | None
    summary: str

    @property
    def n_beads(self) -> int:
        """Number of usable beads."""
        return 0 if self.patches is None else len(self.patches.centers)


def given_beads(image: np.ndarray, positions, detected: Beads | None) -> Beads:
    """A bead table of the user's ``positions`` (N, 2), keeping the hot pixels found by
    the detection (``detected``, None: none searched)."""
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 2 or len(pos) == 0:
        raise ValueError(f"`beads` must be an (N, 2) array of (row, column) positions with "
                         f"N >= 1, got shape {pos.shape}")
    if not np.all(np.isfinite(pos)):
        raise ValueError("`beads` holds NaN or infinite positions")
    h, w = image.shape
    outside = (pos[:, 0] < 0) | (pos[:, 0] > h - 1) | (pos[:, 1] < 0) | (pos[:, 1] > w - 1)
    if outside.any():
        raise ValueError(f"`beads` must lie inside the image (rows 0-{h - 1}, columns "
                         f"0-{w - 1}); {int(outside.sum())} do not, e.g. "
                         f"{pos[outside][0].tolist()}")
    hot = None if detected is None else detected.hot_pixels
    return Beads(pos.copy(), np.ones(len(pos)), hot_pixels=hot)


def image_patches(image: np.ndarray | Callable[[], np.ndarray], psf_radius: float, *,
                  index: int = 0, threshold: float = 8.0,
                  saturation: float | None = None,
                  positions: np.ndarray | None = None,
                  border: float | None = None) -> ImagePatches:
    """The usable bead patches of one image (read here when given as a loader).

    Parameters
    ----------
    image : ndarray of shape (H, W), or a callable returning one
        The image, or a zero-argument loader (so that a task reads its own image and
        no process holds the whole stack).
    psf_radius : float
        PSF radius, pixels (the same for every image of a stack: one patch size).
    index : int
        Position of the image in the stack (for the record).
    threshold, saturation
        As in :func:`~napari_psfspace.core.beads.detect.detect_beads`.
    positions : ndarray of shape (N, 2), optional
        Beads given by the user (row, column), pixels: they replace the detection (hot
        pixels are still masked) and are centred sub-pixel, then checked as detected
        beads are (border, neighbours, saturation).

    Returns
    -------
    ImagePatches
        With ``patches=None`` where no bead is usable (a named skip, not an error).
    """
    raw = image() if callable(image) else image
    img = as_image(raw, copies=ESTIMATE_IMAGES)  # as one image's estimate holds
    r = float(psf_radius)
    try:
        beads = detect_beads(raw, r, threshold=threshold, saturation=saturation)
    except NoBeadsError as err:
        if positions is None:
            return ImagePatches(int(index), img.shape, None, str(err))
        beads = None
    if positions is not None:
        beads = given_beads(img, positions, beads)
    img = beads.clean_image(img)
    kept = np.flatnonzero(beads.kept)
    if len(kept):
        beads.positions[kept] = refine_centers(img, beads.positions[kept],
                                               sigma=centring_sigma(r), half=int(np.ceil(r)))
        flag_unusable(beads, img, r, saturation=None,
                      border=bead_border(r) if border is None else float(border))
        kept = np.flatnonzero(beads.kept)
    if len(kept) == 0:
        return ImagePatches(int(index), img.shape, None, beads.summary())
    # as estimate_operator: a detection too faint to shape the PSF is left out, and a
    # crowded field's patches are cut again with the first model's PSFs as the
    # neighbours' light, so that an image's beads (and its held-out split) are those of
    # its own estimate
    patches, kept = _usable(kept_patches(img, beads, kept, r), kept)
    if patches is not None and len(kept) > FEW_BEADS and crowded(kept, beads.positions,
                                                                 patches.size):
        def cut(light, last):
            new, k = _usable(kept_patches(img, beads, last, r, neighbours=light), last)
            return k, new

        kept, patches = deblend(patches, kept, img, beads, r, cut)
    return ImagePatches(int(index), img.shape, patches, beads.summary())


def _usable(patches: Patches, kept: np.ndarray) -> tuple[Patches | None, np.ndarray]:
    """The patches with light enough to shape the PSF (not faint), and their beads."""
    faint, _ = faint_beads(patches.flux)
    usable = (patches.flux > 0) & ~faint
    return (patches.subset(usable) if usable.any() else None), kept[usable]
