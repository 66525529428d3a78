"""The family's miss: what an image under a condition the family did not see holds beyond
the family's model of its fields (:mod:`.dimensions`' lines, :mod:`.curve`'s curve).

Each field left out in turn and fitted by the model of the others leaves a residual
field; pooled, they give the miss's covariance at a node, its size over the field
(largest at the rim, where the fields are extrapolated from their beads) and its
spatial correlation length (:func:`miss_model`), which :mod:`.coordinates` krige from
an image's beads.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize_scalar

#: Nodes the miss's correlation is measured on (a subset spread over the grid).
CORRELATION_NODES = 300


def miss_model(residuals: np.ndarray, nodes: np.ndarray
               ) -> tuple[np.ndarray, float, np.ndarray]:
    """The miss's covariance at a node (I, I), its correlation length (pixels) and its
    relative standard deviation at each node (G,), from residual fields (K, G, I) at
    ``nodes`` (G, 2).

    The residuals are largest at the rim, where the family's fields are extrapolated
    from their images' beads: the scale is the smooth fit (a quadratic of the position,
    to the log of each node's mean squared residual) scaled to a mean square of 1. The
    length is that of the Gaussian correlation ``exp(-d^2 / 2 ell^2)`` closest to the
    measured one of the residuals divided by their scale, over pairs of nodes.
    """
    k, g, n_i = residuals.shape
    flat = residuals.reshape(-1, n_i)
    cov = flat.T @ flat / (k * g)  # a matrix product: BLAS, not einsum's own loops
    total = float(np.trace(cov))
    if total <= 0 or g < 2:
        return cov, 1.0, np.ones(g)
    scale = _scale_map(np.einsum("kgi,kgi->g", residuals, residuals) / k, nodes)
    step = max(1, g // CORRELATION_NODES)
    sub = np.arange(0, g, step)
    pts = nodes[sub]
    dist = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(axis=-1))
    std = (residuals[:, sub] / scale[None, sub, None]).transpose(1, 0, 2).reshape(len(sub), -1)
    corr = std @ std.T / (k * total)
    span = float(dist.max())
    d2 = dist ** 2

    def cost(log_ell):
        return float(((corr - np.exp(-0.5 * d2 / np.exp(2 * log_ell))) ** 2).sum())

    best = minimize_scalar(cost, bounds=(np.log(span / 200), np.log(span)),
                           method="bounded", options={"xatol": 1e-3})
    return cov, float(np.exp(best.x)), scale


def _scale_map(power: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """A smooth relative standard deviation (G,) from each node's mean squared residual
    (G,): ``exp`` of the least-squares quadratic of the position fitted to its log, its
    mean square 1."""
    span = np.maximum(nodes.max(axis=0) - nodes.min(axis=0), 1e-9)
    u = 2 * (nodes - nodes.min(axis=0)) / span - 1  # -1 to 1
    feats = np.column_stack([np.ones(len(u)), u, u ** 2, u[:, :1] * u[:, 1:]])
    floor = 1e-12 * max(float(power.mean()), 1e-300)
    coef = np.linalg.lstsq(feats, np.log(power + floor), rcond=None)[0]
    var = np.exp(feats @ coef)
    return np.sqrt(var / var.mean())
