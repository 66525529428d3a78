"""What a 3D model looks like: its PSFs on a grid of the field, as one volume and as
sections through focus, ready to display (no GUI here)."""

from __future__ import annotations

import numpy as np

from .operator3d import ProductConvolution3D


def psf_grid_3d(operator: ProductConvolution3D, n: int = 5, *, gap: int = 2,
                gamma: float = 0.5
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 3D PSF at the centres of an ``n x n`` tiling of the field, tiled side by side.

    Each PSF is scaled to its own 3D maximum (planes keep their relative brightness, so
    the focus shows) and raised to ``gamma`` (< 1 lifts the defocused rings).

    Parameters
    ----------
    operator : ProductConvolution3D
    n : int
        PSFs along each side of the field.
    gap : int
        Pixels between tiles.
    gamma : float

    Returns
    -------
    ys, xs : ndarray of shape (n,)
        The positions (pixels).
    volume : ndarray of shape (K, n (P + gap) - gap, n (P + gap) - gap), float32
        The kernels' ``K`` planes (the bead plane at ``K // 2``), tiled laterally.
    sections : ndarray of shape (n (K + gap) - gap, n (P + gap) - gap), float32
        Each PSF's section through its centre row (z down, x across): the focal shift,
        the axial extent and the tilt of the axial profile over the field.
    sections_y : ndarray of the same shape
        The orthogonal sections, through each PSF's centre column (z down, y across).
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"`n` must be a positive integer, got {n!r}")
    _, h, w = operator.image_shape
    k, p, _ = operator.kernel_shape
    ys = (np.arange(n) + 0.5) * h / n - 0.5
    xs = (np.arange(n) + 0.5) * w / n - 0.5
    side = n * (p + gap) - gap
    volume = np.zeros((k, side, side), np.float32)
    sections = np.zeros((n * (k + gap) - gap, side), np.float32)
    sections_y = np.zeros_like(sections)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            kern = np.clip(operator.kernel_at(y, x), 0, None)
            top = kern.max()
            kern = (kern / top) ** gamma if top > 0 else kern
            r0, c0 = i * (p + gap), j * (p + gap)
            volume[:, r0:r0 + p, c0:c0 + p] = kern
            sections[i * (k + gap):i * (k + gap) + k, c0:c0 + p] = kern[:, p // 2, :]
            sections_y[i * (k + gap):i * (k + gap) + k, c0:c0 + p] = kern[:, :, p // 2]
    return ys, xs, volume, sections, sections_y


__all__ = ["psf_grid_3d"]
