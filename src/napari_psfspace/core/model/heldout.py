"""Held-out beads: a spatially spread split, and the residual of a model on them.

A model's error is only honest on beads it never saw. :func:`split_holdout` picks about
a fraction of the beads spread over the whole field (every k-th bead along a Z-order
curve); :func:`heldout_residuals` compares each held-out bead's patch with the model's
PSF at its position, after fitting the bead's amplitude.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..beads.window import bump_window


def morton_order(positions: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Indices sorting positions along a Z-order (Morton) curve over the field."""
    bits = 10
    scale = (2**bits - 1) / np.maximum(np.asarray(shape, float) - 1, 1)
    q = np.clip(np.round(positions * scale), 0, 2**bits - 1).astype(np.uint64)
    code = np.zeros(len(positions), dtype=np.uint64)
    for b in range(bits):
        code |= ((q[:, 0] >> np.uint64(b)) & np.uint64(1)) << np.uint64(2 * b + 1)
        code |= ((q[:, 1] >> np.uint64(b)) & np.uint64(1)) << np.uint64(2 * b)
    return np.argsort(code, kind="stable")


def split_holdout(positions, shape: tuple[int, int], fraction: float = 0.2) -> np.ndarray:
    """Boolean mask of held-out beads, about ``fraction`` of them, spread over the field.

    Parameters
    ----------
    positions : array_like of shape (M, 2)
        Bead positions (row, column) in pixels.
    shape : tuple of int
        Image shape.
    fraction : float
        Fraction held out, in (0, 0.5].

    Returns
    -------
    ndarray of shape (M,), bool
        True for the held-out beads. Deterministic.
    """
    if not 0 < fraction <= 0.5:
        raise ValueError(f"`holdout` must be in (0, 0.5], got {fraction!r}.")
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    order = morton_order(pos, shape)
    step = 1.0 / fraction
    picks = order[(np.floor(np.arange(0, len(pos), step) + step / 2)).astype(int)
                  .clip(0, len(pos) - 1)]
    mask = np.zeros(len(pos), dtype=bool)
    mask[picks] = True
    return mask


@dataclass
class HeldoutResiduals:
    """Per-bead residual of a model on held-out beads.

    Attributes
    ----------
    positions : ndarray of shape (K, 2)
    residual : ndarray of shape (K,)
        ``min_c ||p - c m|| / ||p||`` with ``p`` the bead's windowed, background-free
        patch and ``m`` the model PSF at its position.
    noise_floor : ndarray of shape (K,)
        The value ``residual`` would take for a perfect model: the l2 norm of the
        windowed noise over ``||p||``.
    """

    positions: np.ndarray
    residual: np.ndarray
    noise_floor: np.ndarray

    def summary(self) -> dict:
        """Mean and median residual and noise floor, JSON-ready."""
        if len(self.residual) == 0:
            return {"n_beads": 0}
        return {
            "n_beads": int(len(self.residual)),
            "residual_mean": float(np.mean(self.residual)),
            "residual_median": float(np.median(self.residual)),
            "noise_floor_mean": float(np.mean(self.noise_floor)),
            "noise_floor_median": float(np.median(self.noise_floor)),
        }


def beyond_noise(residual: float, floor: float) -> float:
    """A model's relative error beyond the noise: ``sqrt(residual^2 - floor^2)``, 0 where
    the residual is within the noise."""
    return float(np.sqrt(max(float(residual) ** 2 - float(floor) ** 2, 0.0)))


def beyond_noise_each(residual: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """:func:`beyond_noise` of each bead: residuals and floors (n,) give (n,)."""
    r, f = np.asarray(residual, np.float64), np.asarray(floor, np.float64)
    return np.sqrt(np.maximum(r ** 2 - f ** 2, 0.0))


def median_beyond_noise(residual: np.ndarray, floor: np.ndarray) -> float:
    """:func:`beyond_noise` of beads' residuals and floors (n,), through their squares'
    medians: ``sqrt(median residual^2 - median floor^2)``."""
    r2, f2 = float(np.median(np.square(residual))), float(np.median(np.square(floor)))
    return float(np.sqrt(max(r2 - f2, 0.0)))


def heldout_residuals(operator, patches) -> HeldoutResiduals:
    """Residual of ``operator`` on held-out bead patches.

    Parameters
    ----------
    operator : ProductConvolution
        Model whose ``psf_at`` gives a (P, P) PSF, P equal to the patch size.
    patches : Patches
        Patches of the held-out beads (from :func:`extract_patches` with the same PSF
        radius as the model).

    Returns
    -------
    HeldoutResiduals
    """
    size = patches.size
    if operator.psf_size != size:
        raise ValueError(
            f"The model's PSF size {operator.psf_size} differs from the patch size {size}: "
            "extract the held-out patches with the model's PSF radius."
        )
    models = np.array([operator.psf_at(y, x) for y, x in patches.centers]).reshape(
        len(patches), size, size)
    return residuals_of(models, patches)


def _windowed(patches) -> tuple[np.ndarray, float]:
    """The beads' windowed background-free patches (K, P, P) and the window's norm."""
    win = bump_window(patches.size, patches.r, patches.r_ext)
    return (patches.raw - patches.background) * win, float(np.linalg.norm(win))


def _norms(signal: np.ndarray) -> np.ndarray:
    return np.maximum(np.linalg.norm(signal.reshape(len(signal), -1), axis=1), 1e-300)


def noise_floors(patches) -> np.ndarray:
    """Each bead's noise floor, shape (K,): the norm of its windowed noise over that of
    its windowed patch (the residual a perfect model leaves; 1: the patch is all noise)."""
    signal, win_norm = _windowed(patches)
    return np.asarray(patches.noise, dtype=np.float64) * win_norm / _norms(signal)


def residuals_of(models: np.ndarray, patches) -> HeldoutResiduals:
    """Residual of model PSFs (K, P, P), one per bead, on the beads' patches (as
    :func:`heldout_residuals`, given the PSFs instead of the operator)."""
    signal, win_norm = _windowed(patches)
    norms = _norms(signal)
    res = np.empty(len(patches))
    for k in range(len(patches)):
        model = models[k]
        p = signal[k]
        c = float(np.vdot(model, p) / max(np.vdot(model, model), 1e-300))
        res[k] = float(np.linalg.norm(p - c * model)) / norms[k]
    floor = np.asarray(patches.noise, dtype=np.float64) * win_norm / norms
    return HeldoutResiduals(patches.centers.copy(), res, floor)
