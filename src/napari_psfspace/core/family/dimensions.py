"""How a family's operators vary: the few dimensions its conditions span, learnt with it.

A family of ``K`` images gives ``K`` coefficient fields ``F_k`` (``I`` PSF coefficients
at each of ``G`` nodes). The operators of one microscope vary with a few conditions
(focus, a tilt of the slide, temperature), so a new image's field is modelled in their
few dimensions (:mod:`.coordinates`):

- the mean field ``m`` and the first ``L`` principal directions ``d_l`` of the
  ``F_k - m``, the variance ``v_l`` of each coordinate over the images its prior;
- the family's *miss* ``R``, what an image under a condition the family did not see
  holds beyond those directions: each ``F_j`` fitted at every node by the model of the
  other ``K - 1``, the residuals pooled give its covariance ``C_R`` at a node and its
  spatial correlation length ``ell``.

``L`` is chosen as a user would judge it (:func:`choose_dimensions`): each image of the
family is left out in turn, identified from :data:`N_CLICKS` of its beads by the model of
the others, and compared with its own field; the ``L`` of least error over the images and
draws is kept. The same left-out identifications calibrate the reported spread
(:func:`spread_band`): the ratio of each one's actual error to the error its spread
predicts, whose quantiles make a band. Both go to the family's metadata
(``metadata["dimensions"]``); :func:`family_model` builds the model of a family.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from .coordinates import Model, design, identify_field, relative_field_error

#: Beads a left-out image is identified from when ``L`` is chosen: the paper's "typically
#: 5", the few a user clicks.
N_CLICKS = 5
#: Draws of those beads per left-out image.
N_DRAWS = 4
#: Most directions ``L`` (a family of ``K`` images has at most ``K - 1``).
MAX_DIRECTIONS = 12
#: Nodes the miss's correlation is measured on (a subset spread over the grid).
CORRELATION_NODES = 300
#: Alternations of each fit of the choice (each compares ``L``'s on the same beads: the
#: amplitudes' last digits change no choice).
CHOICE_ITERATIONS = 10
#: Quantiles of the ratio of actual to predicted error that bound the reported band.
BAND_QUANTILES = (0.05, 0.95)


@dataclass
class Beads:
    """One image's beads for the choice of ``L``: positions (P, 2), coefficients on the
    family's basis (P, I), per-pixel noise of each sum-1 patch (P,)."""

    centers: np.ndarray
    coefficients: np.ndarray
    sd: np.ndarray


def family_fields(space: np.ndarray, gammas: np.ndarray) -> np.ndarray:
    """Each image's field at the nodes, (K, G, I), from the spatial basis (J, gy, gx) and
    the ``Gamma_k`` (K, I, J)."""
    s = np.asarray(space, np.float64).reshape(len(space), -1)  # (J, G)
    return np.einsum("jg,kij->kgi", s, np.asarray(gammas, np.float64))


def principal(fields: np.ndarray, n: int | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean (G, I), the first ``n`` principal directions (n, G, I), orthonormal over the
    flattened field, and the variance of each coordinate (n,), of fields (K, G, I)."""
    k = len(fields)
    mean = fields.mean(axis=0)
    dev = (fields - mean).reshape(k, -1)
    most = max(k - 1, 0)
    n = most if n is None else min(int(n), most)
    if n == 0:
        return mean, np.zeros((0, *mean.shape)), np.zeros(0)
    evals, evecs = np.linalg.eigh(dev @ dev.T)  # the K x K Gram matrix: K << G I
    order = np.argsort(evals)[::-1][:n]
    s2 = np.clip(evals[order], 0.0, None)
    # directions at the Gram matrix's round-off (about eps times its largest eigenvalue)
    # are no directions of the fields
    keep = s2 > 1e-12 * max(float(s2[0]), 1e-300)
    s2, order = s2[keep], order[keep]
    dirs = (evecs[:, order].T @ dev) / np.sqrt(s2)[:, None]
    return mean, dirs.reshape(len(s2), *mean.shape), s2 / max(k - 1, 1)


def misses(fields: np.ndarray, n: int) -> np.ndarray:
    """Each field (K, G, I) minus its best fit at every node by the mean and ``n``
    directions of the other fields: the family's miss on conditions it did not see."""
    out = np.empty_like(fields)
    for j in range(len(fields)):
        mean, dirs, _ = principal(np.delete(fields, j, axis=0), n)
        dev = (fields[j] - mean).reshape(-1)
        flat = dirs.reshape(len(dirs), mean.size)
        out[j] = (dev - (flat @ dev) @ flat).reshape(mean.shape)
    return out


def miss_model(residuals: np.ndarray, nodes: np.ndarray) -> tuple[np.ndarray, float]:
    """The miss's covariance at a node (I, I) and its correlation length (pixels) from
    residual fields (K, G, I) at ``nodes`` (G, 2): the length of the Gaussian correlation
    ``exp(-d^2 / 2 ell^2)`` closest to the measured one over pairs of nodes."""
    k, g, n_i = residuals.shape
    cov = np.einsum("kgi,kgj->ij", residuals, residuals) / (k * g)
    total = float(np.trace(cov))
    if total <= 0 or g < 2:
        return cov, 1.0
    step = max(1, g // CORRELATION_NODES)
    sub = np.arange(0, g, step)
    pts = nodes[sub]
    dist = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(axis=-1))
    corr = np.einsum("kai,kbi->ab", residuals[:, sub], residuals[:, sub]) / (k * total)
    span = float(dist.max())
    d2 = dist ** 2

    def cost(log_ell):
        return float(((corr - np.exp(-0.5 * d2 / np.exp(2 * log_ell))) ** 2).sum())

    best = minimize_scalar(cost, bounds=(np.log(span / 200), np.log(span)),
                           method="bounded", options={"xatol": 1e-3})
    return cov, float(np.exp(best.x))


def build_model(fields: np.ndarray, n: int, grid, shape, gram: np.ndarray, *,
                miss: bool = True) -> Model:
    """The model of fields (K, G, I) with ``n`` directions (and the miss's covariance,
    measured by leaving each field out; ``miss=False``: none)."""
    gy, gx = grid
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    mean, dirs, var = principal(fields, n)
    n_i = fields.shape[-1]
    cov, length = np.zeros((n_i, n_i)), 1.0
    if miss and len(fields) >= 3:
        cov, length = miss_model(misses(fields, min(n, len(fields) - 2)), nodes)
    return Model((np.asarray(gy), np.asarray(gx)), tuple(shape), mean, dirs, var, cov,
                 length, np.asarray(gram, np.float64))


def _draws(beads: Beads, seed: int) -> list[np.ndarray]:
    """:data:`N_DRAWS` sets of :data:`N_CLICKS` of an image's beads, seeded."""
    rng = np.random.default_rng(seed)
    n = len(beads.centers)
    return [rng.choice(n, N_CLICKS, replace=False) for _ in range(N_DRAWS)]


def choose_dimensions(fields: np.ndarray, beads: list[Beads | None], grid, shape,
                      gram: np.ndarray, *, seed: int = 0) -> dict:
    """``L`` by leaving each image out and identifying it from a few of its beads, and the
    calibration of the spread at that ``L``.

    Parameters
    ----------
    fields : ndarray of shape (K, G, I)
        The family's fields.
    beads : list of Beads or None
        Each image's beads (None, or fewer than :data:`N_CLICKS`: not left out).
    grid, shape
        The family's nodes and image shape.
    gram : ndarray of shape (I, I)
        The PSF basis's Gram matrix.
    seed : int
        Seeds the draws of beads.

    Returns
    -------
    dict
        ``n_directions``; ``by`` (how it was chosen); ``table`` (each ``L`` tried and
        the mean relative field error of the left-out identifications); ``band``
        (:func:`spread_band`'s calibration, None without left-out images).
    """
    k = len(fields)
    most = min(MAX_DIRECTIONS, k - 2)
    usable = [j for j in range(k) if beads[j] is not None
              and len(beads[j].centers) >= N_CLICKS]
    if most < 1 or not usable:
        n = max(0, min(MAX_DIRECTIONS, k - 1))
        why = ("too few images to leave one out" if most < 1
               else f"no image with {N_CLICKS} beads to leave out")
        return {"n_directions": int(n), "by": f"all the family's directions ({why})",
                "table": [], "band": None}
    errors = np.zeros((most + 1, len(usable) * N_DRAWS))
    for col_j, j in enumerate(usable):
        model = build_model(np.delete(fields, j, axis=0), most, grid, shape, gram,
                            miss=False)
        b = beads[j]
        for d, pick in enumerate(_draws(b, seed + j)):
            at = design(model, b.centers[pick])
            for n in range(most + 1):
                field, _, _ = identify_field(model, b.coefficients[pick], b.sd[pick],
                                             b.centers[pick], n_directions=n, krige=False,
                                             spread=False, at_beads=at,
                                             n_iter=CHOICE_ITERATIONS)
                errors[n, col_j * N_DRAWS + d] = relative_field_error(field, fields[j], gram)
    mean = errors.mean(axis=1)
    best = int(np.argmin(mean))
    table = [{"n": n, "error": round(float(e), 6)} for n, e in enumerate(mean)]
    band = spread_band(fields, beads, usable, best, grid, shape, gram, seed=seed)
    return {"n_directions": best,
            "by": f"leaving each of {len(usable)} images out, identified from {N_CLICKS} of "
                  f"its beads ({N_DRAWS} draws)",
            "table": table, "band": band}


def spread_band(fields: np.ndarray, beads: list[Beads | None], usable: list[int], n: int,
                grid, shape, gram: np.ndarray, *, seed: int = 0) -> dict:
    """The reported spread's calibration: for each left-out identification (as in
    :func:`choose_dimensions`, with the miss), the ratio of its actual error (against
    the image's own field) to the error its spread predicts (the rms over the field's
    central nodes, :attr:`~.coordinates.Model.central`, of the PSF's relative posterior
    standard deviation); the quantiles
    :data:`BAND_QUANTILES` of the ratios scale a prediction into a band."""
    ratios = []
    for j in usable:
        model = build_model(np.delete(fields, j, axis=0), n, grid, shape, gram)
        inside = model.central
        for pick in _draws(beads[j], seed + j):
            b = beads[j]
            field, spread, _ = identify_field(model, b.coefficients[pick], b.sd[pick],
                                              b.centers[pick])
            predicted = float(np.sqrt(np.mean(spread[inside] ** 2)))
            actual = relative_field_error(field, fields[j], gram, inside)
            if predicted > 0 and np.isfinite(actual):
                ratios.append(actual / predicted)
    if not ratios:
        return None
    lo, hi = np.quantile(ratios, BAND_QUANTILES)
    return {"low": float(lo), "high": float(hi), "median": float(np.median(ratios)),
            "n": len(ratios), "quantiles": list(BAND_QUANTILES)}


def family_model(family) -> Model:
    """The few-dimensional model of a family (:class:`~.result.OperatorFamily`), its
    ``L`` the one its learning chose (``metadata["dimensions"]``; a family without:
    all its directions, at most :data:`MAX_DIRECTIONS`). Built once per family."""
    cache = family._cache
    if "model" not in cache:
        fields = family_fields(family.space, family.gammas)
        dims = family.metadata.get("dimensions") or {}
        n = dims.get("n_directions")
        if n is None:
            n = min(MAX_DIRECTIONS, family.n_images - 1)
        flat = family.basis.reshape(family.n_psf, -1)
        cache["model"] = build_model(fields, int(n), family.grid, family.shape,
                                     flat @ flat.T)
    return cache["model"]
