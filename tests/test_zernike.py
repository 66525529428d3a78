"""Tests of the Noll-indexed, rms-normalised Zernike polynomials."""

import numpy as np
import pytest

from napari_psfspace.core.simulation.zernike import noll_to_nm, zernike

NOLL_FIRST_11 = [
    (0, 0),
    (1, 1),
    (1, -1),
    (2, 0),
    (2, -2),
    (2, 2),
    (3, -1),
    (3, 1),
    (3, -3),
    (3, 3),
    (4, 0),
]


def _disk_quadrature(n_rho: int = 24, n_theta: int = 48):
    """Quadrature on the unit disk, exact for the polynomials tested (normalised area 1)."""
    x, w = np.polynomial.legendre.leggauss(n_rho)
    rho = (x + 1) / 2
    w_rho = w / 2 * rho  # Jacobian rho drho
    theta = np.arange(n_theta) * 2 * np.pi / n_theta
    weights = np.outer(w_rho, np.full(n_theta, 2 * np.pi / n_theta)) / np.pi
    rr, tt = np.meshgrid(rho, theta, indexing="ij")
    return rr, tt, weights


def test_noll_to_nm_first_11():
    assert [noll_to_nm(j) for j in range(1, 12)] == NOLL_FIRST_11


def test_noll_to_nm_rejects_zero():
    with pytest.raises(ValueError):
        noll_to_nm(0)


def test_orthonormal_on_unit_disk():
    rr, tt, weights = _disk_quadrature()
    modes = np.array([zernike(j, rr, tt) for j in range(1, 12)])
    gram = np.einsum("iab,jab,ab->ij", modes, modes, weights)
    assert np.abs(gram - np.eye(11)).max() < 1e-8


def test_orthonormal_on_cartesian_grid():
    # Independent (coarse) numerical integration on a pixel grid.
    t = (np.arange(400) + 0.5) / 200 - 1
    yy, xx = np.meshgrid(t, t, indexing="ij")
    rho, theta = np.hypot(yy, xx), np.arctan2(yy, xx)
    inside = rho <= 1
    modes = np.array([zernike(j, rho[inside], theta[inside]) for j in range(1, 12)])
    gram = modes @ modes.T / inside.sum()
    assert np.abs(gram - np.eye(11)).max() < 1e-2


@pytest.mark.parametrize(
    "j, expected",
    [
        (4, lambda r, t: np.sqrt(3) * (2 * r**2 - 1)),
        (5, lambda r, t: np.sqrt(6) * r**2 * np.sin(2 * t)),
        (6, lambda r, t: np.sqrt(6) * r**2 * np.cos(2 * t)),
        (7, lambda r, t: np.sqrt(8) * (3 * r**3 - 2 * r) * np.sin(t)),
        (8, lambda r, t: np.sqrt(8) * (3 * r**3 - 2 * r) * np.cos(t)),
        (11, lambda r, t: np.sqrt(5) * (6 * r**4 - 6 * r**2 + 1)),
    ],
)
def test_closed_forms(j, expected):
    rng = np.random.default_rng(1)
    r, t = rng.uniform(0, 1, 50), rng.uniform(-np.pi, np.pi, 50)
    assert np.abs(zernike(j, r, t) - expected(r, t)).max() < 1e-12


def test_broadcasting():
    out = zernike(6, np.linspace(0, 1, 5)[:, None], np.linspace(0, np.pi, 3)[None, :])
    assert out.shape == (5, 3)
