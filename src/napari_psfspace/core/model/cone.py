"""Keep interpolated PSF coefficients inside the cone of the observed ones.

Paper, Appendix C, "Enforcing realistic PSFs": the coefficients interpolated
independently by thin-plate splines can leave the set of plausible PSFs (negative
lobes far from the beads). Each interpolated vector ``a`` is projected onto the conic
hull of the observed coefficients, ``min_{lambda >= 0} 1/2 ||G^T lambda - a||^2``. The
cone is first reduced to a few generators by a greedy algorithm (start from the mean,
add the observed vector farthest in angle from the current cone, stop below an angle or
at a maximum count). The projection is exact: scipy's active-set NNLS per point of the
coarse grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from ..common.progress import check_halt


def project_onto_cone(points: np.ndarray, generators: np.ndarray) -> np.ndarray:
    """Euclidean projection of each point onto ``cone(generators)``.

    Parameters
    ----------
    points : ndarray of shape (N, I)
        Vectors to project.
    generators : ndarray of shape (k, I)
        Generators of the cone (rows).

    Returns
    -------
    ndarray of shape (N, I)
        The projections: ``lambda @ generators`` with ``lambda >= 0`` the exact
        non-negative least-squares weights of each point (Lawson-Hanson,
        :func:`scipy.optimize.nnls`; the maps are projected on a coarse grid, so one
        solve per point costs little).
    """
    check_halt()
    a = np.asarray(points, dtype=np.float64)
    g = np.asarray(generators, dtype=np.float64)
    if a.ndim != 2 or g.ndim != 2 or a.shape[1] != g.shape[1]:
        raise ValueError(
            f"`points` (N, I) and `generators` (k, I) must share I, got {a.shape} and {g.shape}."
        )
    gt = np.ascontiguousarray(g.T)
    return np.array([nnls(gt, row)[0] for row in a]).reshape(len(a), len(g)) @ g


#: Vectors whose angle :func:`reduce_cone` recomputes at once.
LAZY_CHUNK = 8


@dataclass
class Cone:
    """A polyhedral cone given by a few generators (rows, unit norm)."""

    generators: np.ndarray

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project points (N, I) onto the cone."""
        return project_onto_cone(points, self.generators)

    def angle(self, points: np.ndarray) -> np.ndarray:
        """Angle (radians) between each point (N, I) and the cone."""
        p = np.asarray(points, dtype=np.float64)
        proj = project_onto_cone(p, self.generators)
        cos = np.linalg.norm(proj, axis=1) / np.maximum(np.linalg.norm(p, axis=1), 1e-300)
        return np.arccos(np.clip(cos, -1.0, 1.0))


#: A node's PSF is implausible where its negative mass, as a share of its positive mass,
#: exceeds NEGATIVE_MARGIN times the largest share among the beads' own PSFs (their
#: noise and the basis' truncation give every bead some), and at least NEGATIVE_FLOOR.
NEGATIVE_MARGIN = 1.5
NEGATIVE_FLOOR = 0.02


def negative_share(coefficients: np.ndarray, psfs: np.ndarray, *, chunk: int = 512
                   ) -> np.ndarray:
    """Negative mass over positive mass of each PSF ``coefficients @ psfs``.

    Parameters
    ----------
    coefficients : ndarray of shape (N, I)
    psfs : ndarray of shape (I, ...)
        The basis images.

    Returns
    -------
    ndarray of shape (N,), >= 0
    """
    a = np.asarray(coefficients, dtype=np.float64).reshape(len(coefficients), -1)
    h = np.asarray(psfs, dtype=np.float64).reshape(len(psfs), -1)
    out = np.empty(len(a))
    for i in range(0, len(a), chunk):
        v = a[i:i + chunk] @ h
        pos = np.clip(v, 0, None).sum(axis=1)
        out[i:i + chunk] = -np.clip(v, None, 0).sum(axis=1) / np.maximum(pos, 1e-300)
    return out


def implausible(coefficients: np.ndarray, psfs: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Which of ``coefficients`` (N, I) give PSFs with more negative mass than the beads'
    own (``beta``, (M, I)) allow: bool (N,). See :data:`NEGATIVE_MARGIN`."""
    limit = max(NEGATIVE_MARGIN * float(negative_share(beta, psfs).max(initial=0.0)),
                NEGATIVE_FLOOR)
    return negative_share(coefficients, psfs) > limit


def full_cone(coefficients: np.ndarray) -> Cone:
    """The conic hull of every observed coefficient vector (rows, unit norm): no
    generator dropped."""
    b = np.asarray(coefficients, dtype=np.float64)
    if b.ndim != 2 or len(b) == 0:
        raise ValueError(f"`coefficients` must have shape (M, I) with M > 0, got {b.shape}.")
    return Cone(b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-300))


def reduce_cone(
    coefficients: np.ndarray,
    *,
    max_generators: int = 20,
    angle_tol: float = np.deg2rad(0.5),
) -> Cone:
    """Greedy reduced conic hull of observed coefficient vectors.

    Parameters
    ----------
    coefficients : ndarray of shape (M, I)
        Observed PSF coefficients ``beta`` (one row per bead).
    max_generators : int
        Maximum number of generators (paper: about 20).
    angle_tol : float
        Stop when every observed vector is within this angle (radians) of the cone.

    Returns
    -------
    Cone
    """
    b = np.asarray(coefficients, dtype=np.float64)
    if b.ndim != 2 or len(b) == 0:
        raise ValueError(f"`coefficients` must have shape (M, I) with M > 0, got {b.shape}.")
    unit = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-300)
    mean = unit.mean(axis=0)
    gens = [mean / max(np.linalg.norm(mean), 1e-300)]
    # A vector's angle to the cone never grows as the cone grows, so its last angle
    # bounds its next one: each step recomputes the vectors in decreasing order of their
    # bound, a few at a time, until the largest angle found is at least every remaining
    # bound (lazy greedy). The farthest vector, and whether any lies beyond the
    # tolerance, are then exactly those of recomputing them all.
    bound = np.full(len(unit), np.inf)
    while len(gens) < max_generators:
        cone = Cone(np.array(gens))
        order = np.argsort(-bound, kind="stable")
        best, far, done = -np.inf, -1, 0
        while done < len(order) and bound[order[done]] > max(best, angle_tol):
            part = order[done:done + LAZY_CHUNK]
            part = part[bound[part] > max(best, angle_tol)]
            bound[part] = cone.angle(unit[part])
            top = int(np.argmax(bound[part]))
            if bound[part[top]] > best:
                best, far = float(bound[part[top]]), int(part[top])
            done += LAZY_CHUNK
        if best <= angle_tol:
            break
        gens.append(unit[far])
        bound[far] = 0.0
    return Cone(np.array(gens))
