"""Held-out beads of a 3D model: its error on beads it never saw, against one 3D PSF.

The beads that entered the model are split into ``folds`` groups spread over the field
(every ``folds``-th bead along a Z-order curve,
:func:`~napari_psfspace.core.model.heldout.morton_order`). For each group the model is
learnt again from the other beads' patches, with the model's basis size or the largest
the remaining beads support: the same PCA with outlier rejection, weighted thin-plate
field and cone as :func:`~napari_psfspace.core.volume.estimate3d.estimate_operator_3d`.
Each held-out
bead's windowed 3D patch is compared with the model's PSF at its position, after fitting
its amplitude: ``min_c ||p - c m|| / ||p||``. Its noise floor is the value a perfect
model would reach, ``sqrt(sum_v w_v^2 (s^2 + a c m_v^+)) / ||p||``: the patch's own
background noise ``s`` and the bead's shot noise, ``a`` ADU per photo-electron from the
stack's noise model (:func:`~napari_psfspace.core.beads.noise.noise_model` on the
best-focus plane; 0 where it cannot be measured, and the floor is the background's
alone). On bright beads the shot noise is most of it.

The simpler baseline is scored the same way: one 3D PSF for the whole field, the mean of
the training beads' patches (what PSF-Extractor or an averaging distiller makes). A field
model that does not beat it on held-out beads is not worth its kernels; the result says
which is better (``field_wins``).
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from ..beads.noise import noise_model
from ..beads.window import bump_window, radial_distance
from ..common.progress import Progress, wait_with_progress
from ..common.twins import drained
from ..model.field import keep_in_cone
from ..model.heldout import morton_order
from ..model.pca import learn_basis, min_beads_for
from ..model.tps import ThinPlateSpline
from ..model.voronoi import voronoi_areas

#: Groups of held-out beads.
FOLDS = 5


@dataclass
class Heldout3D:
    """Held-out residuals of a 3D model and of one 3D PSF on the same beads.

    Attributes
    ----------
    positions : ndarray of shape (K, 2)
    residual : ndarray of shape (K,)
        The field model's relative residual on each held-out bead.
    single : ndarray of shape (K,)
        One 3D PSF's (the mean of the training beads).
    noise_floor : ndarray of shape (K,)
    gain : float
        ``a`` of the shot noise in the floor (ADU per photo-electron; 0: background only).
    noise_kind : str
        How ``a`` was obtained (the noise model's kind).
    """

    positions: np.ndarray
    residual: np.ndarray
    single: np.ndarray
    noise_floor: np.ndarray
    gain: float = 0.0
    noise_kind: str = ""

    def summary(self) -> dict:
        """Medians, the ratio to the noise floor, and whether the field model wins."""
        if len(self.residual) == 0:
            return {"n_beads": 0}
        med = float(np.median(self.residual))
        floor = float(np.median(self.noise_floor))
        return {"n_beads": int(len(self.residual)), "residual_median": med,
                "single_median": float(np.median(self.single)),
                "noise_floor_median": floor,
                "over_floor": med / max(floor, 1e-300),
                "field_wins": bool(med <= float(np.median(self.single))),
                "gain": self.gain, "noise_kind": self.noise_kind}


def _fit(model: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    """``(residual, c)`` of the best amplitude ``c``."""
    c = float(np.vdot(model, p) / max(np.vdot(model, model), 1e-300))
    return float(np.linalg.norm(p - c * model) / max(np.linalg.norm(p), 1e-300)), c


def iter_heldout_error_3d(estimation, stack, *, folds: int = FOLDS,
                          smoothing: float | None = None
                          ) -> Generator[Progress, None, Heldout3D]:
    """The held-out residuals of a 3D estimate (the module's notes).

    :func:`iter_heldout_error_3d` is its generator form (progress after each fold).

    Parameters
    ----------
    estimation : Estimation3D
        From :func:`~napari_psfspace.core.volume.estimate3d.iter_estimate_operator_3d`.
    stack : array_like of shape (Z, H, W)
        The stack it was learnt from (its lateral shape, and the noise model of its
        best-focus plane).
    folds : int
        Groups of held-out beads (>= 2).
    smoothing : float, optional
        The thin-plate smoothing (default: chosen from the data, as the estimate).

    Yields
    ------
    Progress
        A record after each step; stopping the generator there cancels the run.

    Returns
    -------
    Heldout3D
    """
    if int(folds) != folds or folds < 2:
        raise ValueError(f"`folds` must be an integer >= 2, got {folds!r}")
    patches = estimation.patches.subset(estimation.basis.inliers)
    # the estimate's rule for the cone (chosen on all its beads), in every fold
    constraint = (estimation.operator.metadata.get("field_constraint") or {}).get(
        "chosen", "cone")
    n = len(patches)
    n_psf = int(estimation.operator.n_psf)
    h, w = np.shape(stack)[1:]
    focus = int(estimation.operator.metadata.get("focus_slice", estimation.operator.plane))
    nm = noise_model(np.asarray(stack[focus]))
    gain = float(nm.gain) if np.isfinite(nm.gain) and nm.gain > 0 else 0.0
    order = morton_order(patches.centers, (h, w))
    group = np.empty(n, int)
    group[order] = np.arange(n) % int(folds)
    inside = patches.data_planes(estimation.operator.image_shape[0])
    support = inside[:, None, None] & (radial_distance(patches.size) < patches.r_ext)[None]
    win2 = np.broadcast_to(bump_window(patches.size, patches.r, patches.r_ext) ** 2,
                           patches.psf.shape[1:]) * inside[:, None, None]
    res, single, floor, pos = [], [], [], []
    for f in range(int(folds)):
        yield Progress("held-out", f / int(folds), f"held-out beads: fold {f + 1} of "
                                                   f"{int(folds)}")
        test, train = group == f, group != f
        # the largest basis the fold's training beads support, at most the model's: a
        # fold of a model whose basis uses nearly every bead is still scored (with a
        # smaller basis: the figure errs on the pessimistic side)
        n_fold = min(n_psf, max((int(train.sum()) - 2) // 2, 0))
        if test.sum() == 0 or n_fold < 1 or train.sum() < min_beads_for(n_fold):
            continue  # too few beads left for any basis: the fold is skipped
        basis = yield from wait_with_progress(
            lambda train=train, n_fold=n_fold: learn_basis(patches.psf[train], n_fold,
                                                           support=support),
            Progress("held-out", f / int(folds), f"held-out beads: fold {f + 1} of "
                                                 f"{int(folds)}"))
        centers = patches.centers[train][basis.inliers]
        spline = ThinPlateSpline(centers, basis.coefficients,
                                 weights=voronoi_areas(centers, (h, w)),
                                 smoothing=smoothing, scale=0.5 * float(np.hypot(h, w)))
        coef, _ = keep_in_cone(np.asarray(spline(patches.centers[test]), np.float64)
                               .reshape(int(test.sum()), -1), basis.coefficients,
                               basis.basis, constraint)
        models = np.tensordot(coef, basis.basis, axes=(1, 0))  # (k, Zp, P, P)
        mean = patches.psf[train].mean(axis=0)
        for k, j in enumerate(np.flatnonzero(test)):
            p = patches.psf[j] * patches.flux[j]  # the windowed, background-free patch
            r, c = _fit(models[k], p)
            res.append(r)
            single.append(_fit(mean, p)[0])
            # the window multiplies the signal: the unwindowed model is c m / w
            shot = gain * np.clip(c * models[k], 0, None) / np.maximum(np.sqrt(win2), 1e-12)
            var = float(np.sum(win2 * (patches.noise[j] ** 2 + shot)))
            floor.append(np.sqrt(var) / max(np.linalg.norm(p), 1e-300))
            pos.append(patches.centers[j])
    return Heldout3D(np.asarray(pos).reshape(-1, 2), np.asarray(res), np.asarray(single),
                     np.asarray(floor), gain, str(nm.kind))


heldout_error_3d = drained(iter_heldout_error_3d, "heldout_error_3d")


__all__ = ["FOLDS", "Heldout3D", "heldout_error_3d", "iter_heldout_error_3d"]
