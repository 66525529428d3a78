"""The small field the family-model tests draw their fields on: a 256 x 256 image, a 9 x 9
grid of nodes, 6 PSF coefficients."""

import numpy as np

SHAPE = (256, 256)
GRID = (np.linspace(0, 255, 9), np.linspace(0, 255, 9))
N_I = 6


def nodes() -> np.ndarray:
    """The grid's nodes (81, 2), row-major."""
    gy, gx = GRID
    return np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
