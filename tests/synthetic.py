"""Synthetic test images shared by the core tests (known ground truth)."""

import numpy as np
from scipy.special import erf


def integrated_gaussian(shape, center, sigma, amplitude):
    """Pixel-integrated isotropic Gaussian of total flux ``amplitude``, shape ``shape``,
    centred at ``center`` (row, column) in pixels (pixel centres at integers)."""
    def axis(n, c):
        edges = np.arange(n + 1) - 0.5 - c
        return 0.5 * np.diff(erf(edges / (np.sqrt(2) * sigma)))

    return amplitude * np.outer(axis(shape[0], center[0]), axis(shape[1], center[1]))
