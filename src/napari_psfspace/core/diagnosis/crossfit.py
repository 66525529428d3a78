"""Cross-fitted residuals: every bead judged by a model that never saw it.

The beads are split into ``k`` folds spread over the field (every k-th bead along a
Z-order curve, so each fold is a spatially spread ~1/k of the beads). For each fold a
model is estimated without it (its beads still count as neighbours of the others), and
the fold's beads are fitted with that model
(:func:`~napari_psfspace.core.diagnosis.residuals.fit_beads`).
With ``k = 5`` each fold is a 20 % hold-out, as one split would keep; together the folds give
held-out residuals for *all* beads, which makes before/after comparisons paired and
powerful.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from ..beads.detect import COMPANION, HELDOUT, KEPT, Beads
from ..beads.noise import NoiseModel
from ..common.progress import Progress, run_with_progress
from ..common.threads import blas_threads
from ..model.estimate import iter_estimate
from ..model.heldout import morton_order
from .residuals import BeadResiduals, fit_beads


@dataclass
class CrossFit:
    """Cross-fitted residuals.

    Attributes
    ----------
    residuals : BeadResiduals
        One entry per bead, in the order of ``bead_index``.
    bead_index : ndarray of shape (K,)
        Index into the bead table of each entry.
    fold : ndarray of shape (K,)
        Fold of each entry.
    model_meta : dict or None
        Basis size and smoothing of the first fold's model (what the model uses).
    """

    residuals: BeadResiduals
    bead_index: np.ndarray
    fold: np.ndarray
    model_meta: dict | None = None

    def summary(self) -> dict:
        return self.residuals.summary()


def assign_folds(positions, shape, k: int = 5) -> np.ndarray:
    """Fold (0 .. k-1) of each position: every k-th along a Z-order curve."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    order = morton_order(pos, shape)
    fold = np.empty(len(pos), dtype=int)
    fold[order] = np.arange(len(pos)) % k
    return fold


@blas_threads
def iter_crossfit(
    image,
    beads: Beads,
    noise: NoiseModel,
    *,
    psf_radius: float,
    folds: int = 5,
    estimate_kwargs: dict | None = None,
    fit_kwargs: dict | None = None,
    fit_image=None,
) -> Generator[Progress, None, CrossFit]:
    """Generator: estimate ``folds`` models, each without one fold; fit that fold.

    Parameters
    ----------
    image : array_like of shape (M, N)
        The image the models are estimated from (possibly corrected by effects).
    beads : Beads
        Beads with sub-pixel positions; those with status "kept" are cross-fitted, and
        those with status "companion" are judged too but never learnt from.
    noise : NoiseModel
    psf_radius : float
    folds : int
    estimate_kwargs : dict, optional
        Passed to :func:`~napari_psfspace.core.model.estimate.iter_estimate`.
    fit_kwargs : dict, optional
        Passed to :func:`~napari_psfspace.core.diagnosis.residuals.fit_beads`.
    fit_image : array_like, optional
        The image the beads are fitted on (default ``image``).

    Returns
    -------
    CrossFit
    """
    est_kw = {"holdout": None, **(estimate_kwargs or {})}
    fit_kw = fit_kwargs or {}
    img = np.asarray(image)
    target = img if fit_image is None else np.asarray(fit_image)
    # judged: kept beads, and beads with a companion (fitted jointly, never learnt from)
    kept = np.flatnonzero((beads.status == KEPT) | (beads.status == COMPANION))
    fold_of = assign_folds(beads.positions[kept], img.shape, folds)
    parts, index, fold_ids = [], [], []
    meta = None
    for f in range(folds):
        held = kept[fold_of == f]
        if len(held) == 0:
            continue
        status = beads.status.copy()
        status[held[status[held] == KEPT]] = HELDOUT
        train = beads.copy(status)
        est = run_with_progress(iter_estimate(img, psf_radius=psf_radius, beads=train,
                                              motion_test=False, **est_kw))
        if meta is None:
            m = est.operator.metadata
            meta = {"n_psf": m.get("n_psf"), "smoothing": m.get("smoothing")}
        parts.append(fit_beads(target, beads.positions[held], est.operator, noise, **fit_kw))
        index.append(held)
        fold_ids.append(np.full(len(held), f))
        yield Progress("cross-fit", (f + 1) / folds, f"fold {f + 1}/{folds}: "
                       f"{len(held)} beads held out")
    return CrossFit(BeadResiduals.concatenate(parts), np.concatenate(index),
                    np.concatenate(fold_ids), meta)
