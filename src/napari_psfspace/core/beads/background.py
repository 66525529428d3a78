"""Per-patch background removal by a low-order polynomial (paper, Appendix B).

The pixels farther than ``r`` from the patch centre hold only background and noise; a
polynomial of order 2 (monomials 1, x, y, xy, x², y²) is fitted to them by least squares
and subtracted from the whole patch. The fit is one pseudo-inverse shared by all
patches, so it costs one matrix product for any number of beads.
"""

from __future__ import annotations

import numpy as np

from .window import radial_distance

#: Highest order of the background of a patch cut by the image's edge: a quadratic fitted
#: on one side of the bead extrapolates under it.
PARTIAL_ORDER = 1


def monomials(size: int, order: int = 2) -> np.ndarray:
    """Monomials ``x**a * y**b`` with ``a + b <= order`` on a patch, coordinates in [-1, 1].

    Returns
    -------
    ndarray of shape (size * size, n_monomials)
    """
    if order < 0:
        raise ValueError(f"`order` must be >= 0, got {order}.")
    u = np.linspace(-1.0, 1.0, size)
    yy, xx = np.meshgrid(u, u, indexing="ij")
    cols = [xx**a * yy**b for total in range(order + 1) for a in range(total + 1)
            for b in [total - a]]
    return np.stack([c.ravel() for c in cols], axis=1)


def fit_background(patches: np.ndarray, r: float, *, order: int = 2,
                   observed: np.ndarray | None = None) -> np.ndarray:
    """Fit and return the polynomial background of each patch.

    Parameters
    ----------
    patches : ndarray of shape (K, P, P)
        Patches centred on the beads (centre pixel ``P // 2``).
    r : float
        Radius in pixels beyond which a patch holds background only.
    order : int
        Polynomial order (2 in the paper).
    observed : ndarray of shape (K, P, P), bool, optional
        The pixels that lie in the image (a bead near the border: its patch reaches
        past the edge). The background is fitted on the observed pixels beyond ``r``
        only, at most a plane (:data:`PARTIAL_ORDER`) and a lower order where they are
        too few (order 0 at least: their median). Default: all.

    Returns
    -------
    ndarray of shape (K, P, P), same dtype as ``patches``
        The fitted background of each patch, evaluated on the whole patch.

    Raises
    ------
    ValueError
        When fewer pixels lie outside ``r`` than the polynomial has coefficients.
    """
    k, p, p2 = patches.shape
    if p != p2:
        raise ValueError(f"`patches` must be square, got shape {patches.shape}.")
    design = monomials(p, order)
    outside = radial_distance(p).ravel() > r
    if np.count_nonzero(outside) < 2 * design.shape[1]:
        raise ValueError(
            f"Patch of size {p} has only {np.count_nonzero(outside)} pixels outside the PSF "
            f"radius {r:g}: too few to fit a background polynomial of order {order}."
        )
    pinv = np.linalg.pinv(design[outside])  # (n_monomials, n_outside)
    flat = patches.reshape(k, p * p)
    coef = flat[:, outside] @ pinv.T  # (K, n_monomials)
    out = (coef @ design.T).reshape(k, p, p)
    if observed is not None:
        seen = np.asarray(observed, bool).reshape(k, p * p)
        for i in np.flatnonzero(~seen[:, outside].all(axis=1)):
            use = outside & seen[i]
            n = int(np.count_nonzero(use))
            # a ring cut by the edge pins a curvature on one side only: at most a plane
            for o in range(min(order, PARTIAL_ORDER), -1, -1):
                m = (o + 1) * (o + 2) // 2
                if n >= 2 * m or o == 0:
                    break
            if n == 0:  # nothing beyond r in the image: the patch's own lowest level
                out[i] = np.min(flat[i, seen[i]]) if seen[i].any() else 0.0
                continue
            if o == 0:
                out[i] = np.median(flat[i, use])
                continue
            d = design[:, :m]
            c, *_ = np.linalg.lstsq(d[use], flat[i, use], rcond=None)
            out[i] = (d @ c).reshape(p, p)
    return out.astype(patches.dtype, copy=False)
