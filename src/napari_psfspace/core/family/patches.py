"""One image's contribution to a subspace: its beads' patches (step 1 of section 2.4).

The beads stage as the single-image estimate runs it (detection with hot pixels masked,
sub-pixel centring, rejection of beads that moved to the border, windowed background-free
patches), without learning anything: the basis is learnt from the patches of all
images together. Runs as one dask task per image.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass

import numpy as np

from ..beads.centering import refine_centers
from ..beads.detect import Beads, NoBeadsError, detect_beads, flag_unusable
from ..beads.patches import Patches
from ..common.progress import Progress, wait_with_progress
from ..common.spacing import bead_border, centring_sigma
from ..common.threads import compute_tasks
from ..common.validate import as_image, check_grid_step
from ..model.deblend import crowded, deblend
from ..model.estimate import ESTIMATE_IMAGES, faint_beads, kept_patches
from ..model.fewbeads import FEW_BEADS
from ..model.heldout import split_holdout
from ..model.pca import min_beads_for


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


def extract_patches(items: list, psf_radius: float, *, threshold: float, client,
                    chunk: int) -> Generator[Progress, None, list[ImagePatches]]:
    """Each image's beads and patches (:func:`image_patches`), as dask tasks of ``chunk``
    images each (threads, or the cluster's workers); a record after each chunk."""
    import dask

    tasks = [dask.delayed(image_patches)(item, float(psf_radius), index=k, threshold=threshold)
             for k, item in enumerate(items)]
    found: list[ImagePatches] = []
    step = max(1, int(chunk))
    for start in range(0, len(tasks), step):
        found += yield from wait_with_progress(
            lambda part=tasks[start:start + step]: compute_tasks(part, client),
            Progress("patches", 0.6 * len(found) / len(tasks),
                     f"{len(found)} of {len(tasks)} images: beads being extracted"))
        yield Progress("patches", 0.6 * len(found) / len(tasks),
                       f"{len(found)} of {len(tasks)} images: "
                       f"{sum(f.n_beads for f in found)} beads")
    return found


def usable_images(found: list[ImagePatches], grid_step: float, n_psf
                  ) -> tuple[tuple[int, int], list[ImagePatches], dict]:
    """The images' shape (one for all), the images with usable beads and the skipped
    ones' summaries, by index; one clear line where they cannot make a family."""
    shapes = {f.shape for f in found}
    if len(shapes) > 1:
        first = found[0].shape
        odd = next(f for f in found if f.shape != first)
        raise ValueError(f"every image of `images` must have the same shape: image 0 is "
                         f"{first}, image {odd.index} is {odd.shape}")
    check_grid_step(grid_step, found[0].shape)
    shape = found[0].shape
    used = [f for f in found if f.patches is not None]
    skipped = {f.index: f.summary for f in found if f.patches is None}
    if len(used) < 2:
        raise ValueError(f"at least 2 images with usable beads are needed, got {len(used)} "
                         f"of {len(found)} (no usable bead in images {sorted(skipped)})")
    n_total = sum(f.n_beads for f in used)
    if n_total < min_beads_for(1):
        raise ValueError(
            f"a family needs at least {min_beads_for(1)} usable beads over all images, got "
            f"{n_total} (beads per image with any: "
            f"{ {f.index: int(f.n_beads) for f in used} }): use brighter or more bead images")
    if n_psf is not None and n_total < min_beads_for(int(n_psf)):
        raise ValueError(
            f"`n_psf` = {n_psf} needs at least {min_beads_for(int(n_psf))} usable beads over "
            f"all images, got {n_total}: lower `n_psf` or use more beads")
    return shape, used, skipped


def hold_out(used: list[ImagePatches], shape: tuple[int, int], holdout: float | None
             ) -> tuple[dict[int, Patches], list[ImagePatches]]:
    """About ``holdout`` of each image's beads (spread over the field; none of an image
    with fewer than 5) held out to judge its operator, by image; each image with the
    rest of its beads."""
    held: dict[int, Patches] = {}
    train: list[ImagePatches] = []
    for i, f in enumerate(used):
        mask = (split_holdout(f.patches.centers, shape, holdout)
                if holdout and f.n_beads >= 5 else np.zeros(f.n_beads, bool))
        if mask.any() and (~mask).any():
            held[i] = f.patches.subset(mask)
            f = ImagePatches(f.index, f.shape, f.patches.subset(~mask), f.summary)
        train.append(f)
    return held, train
