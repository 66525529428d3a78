"""How a family's operators vary: the few dimensions its conditions span, learnt with it.

A family of ``K`` images gives ``K`` coefficient fields ``F_k`` (``I`` PSF coefficients
at each of ``G`` nodes). The operators of one microscope vary with a few conditions
(focus, a tilt of the slide, temperature), so a new image's field is modelled in their
few dimensions (:mod:`.coordinates`):

- the mean field ``m`` and the first ``L`` principal directions ``d_l`` of the
  ``F_k - m``, the variance ``v_l`` of each coordinate over the images its prior;
- the first ``M`` of those coordinates also varying as planes over the field
  (:func:`planar`): a tilted slide puts each part of the field under another focus, so
  an image between those learnt is their mix in proportions that change across it;
- the family's *miss* ``R``, what an image under a condition the family did not see
  holds beyond that model: each ``F_j`` fitted at every node by the model of the other
  ``K - 1``, the residuals pooled give its covariance ``C_R`` at a node, its size over
  the field (largest at the rim, where the fields are extrapolated from the beads) and
  its spatial correlation length ``ell``.

``L`` and ``M`` are chosen as a user would judge them (:func:`choose_dimensions`): each
image of the family is left out in turn, identified from :data:`N_CLICKS` of its beads
by the model of the others, and compared with its own field; the sizes of least error
over the images and draws are kept. A curve (:mod:`.curve`: the fields as a quadratic
in one condition varying as a plane over the field, three numbers an image) is judged
on the same draws and is kept unless the lines' errors are clearly lower
(:func:`choose_kind`: the lines' sizes are the least of many on those draws, a minimum
the draws' chance biases low). A clicked bead's
coefficients stray from its image's field by more than its background's noise says (its
own shot noise, its centring, its background's fit): :func:`noise_factor` measures by how
much on the family's own beads, and every bead's noise is scaled by it, in the choice and
when an image is identified. The same left-out
identifications calibrate the reported spread (:func:`spread_band`): the ratio of each
one's actual error to the error its spread predicts, whose quantiles make a band. Both
go to the family's metadata (``metadata["dimensions"]``); :func:`family_model` builds
the model of a family.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..common.threads import map_threads
from .coordinates import (
    Model,
    bilinear,
    design,
    krige_miss,
    relative_field_error,
    relative_field_errors,
    solve_nested,
    spread_at,
    whitened,
    whitener,
)
from .curve import (
    DEGREES,
    MIN_IMAGES,
    Curve,
    build_curve,
    curve_misses,
    identify_any,
    learn_thetas,
)
from .miss import miss_model

#: Beads a left-out image is identified from when ``L`` is chosen: the paper's "typically
#: 5", the few a user clicks.
N_CLICKS = 5
#: Draws of those beads per left-out image.
N_DRAWS = 3
#: Most directions ``L`` (a family of ``K`` images has at most ``K - 1``).
MAX_DIRECTIONS = 12
#: Most of the directions whose coordinates also vary as planes over the field.
MAX_PLANAR = 1
#: The prior standard deviation of a coordinate's slope across the field (from one side
#: to the other), in units of the coordinate's own.
PLANAR_SCALE = 1.0
#: Alternations of each fit of the choice (each compares ``L``'s on the same beads: the
#: amplitudes' last digits change no choice).
CHOICE_ITERATIONS = 10
#: The weights of the family's miss in a clicked bead's residual on a curve tried
#: (:meth:`.curve.Curve.bead_whiteners`); the one of least left-out error is kept. A
#: clicked bead strays from its image's field by several times the miss (its centring,
#: its background), so the weights start at 10.
MISS_FACTORS = (10.0, 30.0)
#: Steps of a left-out image's curve, from the whole family's ``theta``.
CURVE_LEFT_OUT_ITERATIONS = 5
#: Quantiles of the ratio of actual to predicted error that bound the reported band.
BAND_QUANTILES = (0.05, 0.95)


@dataclass
class Beads:
    """One image's beads for the choice of ``L``: positions (P, 2), coefficients on the
    family's basis (P, I), per-pixel noise of each sum-1 patch (P,)."""

    centers: np.ndarray
    coefficients: np.ndarray
    sd: np.ndarray


def noise_factor(fields: np.ndarray, beads: list[Beads | None], grid, gram: np.ndarray
                 ) -> float:
    """How many times its noise ``sd`` a bead's coefficients stray from its image's
    field, measured on the family's own beads: one where none can be measured.

    Each bead's whitened residual about its image's field at it (bilinear between the
    nodes, the bead's amplitude fitted) over ``sd`` squared, ``q``; with noise ``f sd``
    in each of the ``I`` whitened coefficients, ``q`` is ``f^2`` times a chi-square of
    ``I - 1`` degrees of freedom (one taken by the amplitude), so ``f`` is the root of
    the median ``q`` over that chi-square's median (a median: a doublet or a bead on a
    structure among hundreds moves it little). The image's field is learnt from the
    same beads, which makes ``q`` a little small, and is itself off the truth, which
    makes it large: beside faint beads' noise both are small, beside bright beads' the
    second makes ``f`` somewhat too large (their kriged miss a little too smooth).
    """
    from scipy.stats import chi2

    white = whitener(gram).T
    n_i = len(gram)
    qs = []
    for field, b in zip(fields, beads, strict=True):
        if b is None or not len(b.centers):
            continue
        f = bilinear(grid, b.centers) @ field  # (P, I)
        c = np.asarray(b.coefficients, np.float64)
        fw, cw = f @ white, c @ white
        g = (cw * fw).sum(axis=1) / np.maximum((fw * fw).sum(axis=1), 1e-300)
        res = cw - g[:, None] * fw
        ok = np.isfinite(b.sd) & (b.sd > 0)
        qs.append((res[ok] ** 2).sum(axis=1) / b.sd[ok] ** 2)
    q = np.concatenate(qs) if qs else np.zeros(0)
    if n_i < 2 or len(q) < N_CLICKS:
        return 1.0
    factor = float(np.sqrt(np.median(q) / chi2.median(n_i - 1)))
    return factor if np.isfinite(factor) and factor > 0 else 1.0


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


def planar(mean: np.ndarray, dirs: np.ndarray, variances: np.ndarray, n_planar: int,
           nodes: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """The directions (n + 2 m, G, I) and their prior variances of a model whose first
    ``m = n_planar`` coordinates also vary over the field as planes: each of those
    directions times the scaled row and column (-0.5 to 0.5 across the image), its
    variance the direction's times :data:`PLANAR_SCALE` squared."""
    m = min(int(n_planar), len(dirs))
    if m == 0:
        return dirs, variances
    rel = nodes / np.maximum(np.asarray(shape, np.float64) - 1, 1) - 0.5  # (G, 2)
    lead = dirs[:m]
    out = np.concatenate([dirs, lead * rel[None, :, 0:1], lead * rel[None, :, 1:2]])
    tilt = PLANAR_SCALE ** 2 * variances[:m]
    return out, np.concatenate([variances, tilt, tilt])


def misses(fields: np.ndarray, n: int, n_planar: int = 0, nodes: np.ndarray | None = None,
           shape=None) -> np.ndarray:
    """Each field (K, G, I) minus its best fit at every node by the model of the other
    fields (their mean, ``n`` directions, the first ``n_planar`` of them also varying as
    planes over the field at ``nodes`` of an image of ``shape``): the family's miss on
    conditions it did not see."""
    out = np.empty_like(fields)
    for j in range(len(fields)):
        mean, dirs, var = principal(np.delete(fields, j, axis=0), n)
        if n_planar:
            dirs, _ = planar(mean, dirs, var, n_planar, nodes, shape)
        dev = (fields[j] - mean).reshape(-1)
        flat = dirs.reshape(len(dirs), mean.size)
        if not len(flat):
            out[j] = fields[j] - mean
            continue
        # least squares by the small normal equations (the planar directions are not
        # orthogonal to the others)
        coef = np.linalg.lstsq(flat @ flat.T, flat @ dev, rcond=None)[0]
        out[j] = (dev - coef @ flat).reshape(mean.shape)
    return out


def build_model(fields: np.ndarray, n: int, grid, shape, gram: np.ndarray, *,
                n_planar: int = 0, miss: bool = True) -> Model:
    """The model of fields (K, G, I) with ``n`` directions, the first ``n_planar`` of them
    also varying as planes over the field (:func:`planar`), and the miss's covariance
    (measured by leaving each field out; ``miss=False``: none)."""
    gy, gx = grid
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    mean, dirs, var = principal(fields, n)
    dirs, var = planar(mean, dirs, var, n_planar, nodes, shape)
    n_i = fields.shape[-1]
    cov, length, scale = np.zeros((n_i, n_i)), 1.0, None
    if miss and len(fields) >= 3:
        cov, length, scale = miss_model(misses(fields, min(n, len(fields) - 2),
                                               min(n_planar, n, len(fields) - 2), nodes,
                                               shape), nodes)
    return Model((np.asarray(gy), np.asarray(gx)), tuple(shape), mean, dirs, var, cov,
                 length, np.asarray(gram, np.float64), scale)


def _columns(n: int, m: int, most: int, most_planar: int) -> np.ndarray:
    """The directions of a model with ``n`` directions, ``m`` of them planar, among those
    of :func:`build_model` with ``most`` directions and ``most_planar`` planar ones: the
    first ``n``, then the first ``m`` row slopes and the first ``m`` column slopes."""
    return np.r_[np.arange(n), most + np.arange(m), most + most_planar + np.arange(m)]


def _draws(beads: Beads, seed: int) -> list[np.ndarray]:
    """:data:`N_DRAWS` sets of :data:`N_CLICKS` of an image's beads, seeded."""
    rng = np.random.default_rng(seed)
    n = len(beads.centers)
    return [rng.choice(n, N_CLICKS, replace=False) for _ in range(N_DRAWS)]


def choose_dimensions(fields: np.ndarray, beads: list[Beads | None], grid, shape,
                      gram: np.ndarray, *, seed: int = 0) -> dict:
    """``L`` and ``M`` by leaving each image out and identifying it from a few of its
    beads, and the calibration of the spread there.

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
        ``kind`` (``"curve"`` unless the lines' left-out errors at their ``L`` and ``M``
        are :func:`clearly_lower` than the curve's, then ``"lines"``); ``n_directions``
        (``L``) and ``n_planar`` (``M``: the first ``M`` directions' coordinates also
        vary as planes over the field, as a tilted slide makes the focus do; 1 and 1
        for a curve); ``by`` (how they were chosen); ``table`` (each ``n`` and ``planar``
        tried and the left-out identifications' mean relative field error, ``error``; the
        curve's row also holds its degree, ``curve``, and each degree's ``degree_errors``);
        ``curve`` (a chosen curve's ``degree`` and its images' ``thetas``, K x 3);
        ``band`` (:func:`spread_band`'s calibration, None without left-out images).
    """
    k = len(fields)
    most = min(MAX_DIRECTIONS, k - 2)
    usable = [j for j in range(k) if beads[j] is not None
              and len(beads[j].centers) >= N_CLICKS]
    if most < 1 or not usable:
        n = max(0, min(MAX_DIRECTIONS, k - 1))
        why = ("too few images to leave one out" if most < 1
               else f"no image with {N_CLICKS} beads to leave out")
        return {"n_directions": int(n), "n_planar": 0,
                "by": f"all the family's directions ({why})", "table": [], "band": None}
    sizes = [(n, m) for n in range(most + 1) for m in range(min(n, MAX_PLANAR) + 1)]
    errors = np.zeros((len(sizes), len(usable) * N_DRAWS))
    white = whitener(gram).T  # fields times it: the PSF's l2 norm
    gy, gx = grid
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    zero = np.zeros((len(gram), len(gram)))
    for col_j, j in enumerate(usable):
        mean, dirs, var = principal(np.delete(fields, j, axis=0), most)
        n_c, m_c = len(dirs), min(MAX_PLANAR, len(dirs))  # fewer where the fields are
        dirs, var = planar(mean, dirs, var, m_c, nodes, shape)
        full = Model((np.asarray(gy), np.asarray(gx)), tuple(shape), mean, dirs, var, zero,
                     1.0, gram)
        truth = fields[j] @ white
        mean_w = full.mean @ white
        dirs_w = full.directions @ white  # (L + 2 M, G, I), whitened
        b = beads[j]
        masks = np.zeros((len(sizes), len(dirs)), bool)
        for row, (n, m) in enumerate(sizes):
            masks[row, _columns(min(n, n_c), min(m, m_c, n), n_c, m_c)] = True
        for d, pick in enumerate(_draws(b, seed + j)):
            base, a = design(full, b.centers[pick])
            cw, bw, aw = whitened(gram, b.coefficients[pick], base, a)
            # every size at once: each uses a subset of the same directions
            z = solve_nested(cw, bw, aw, b.sd[pick], full.variances, masks,
                             n_iter=CHOICE_ITERATIONS)
            field = mean_w[None] + np.tensordot(z, dirs_w, axes=1)
            errors[:, col_j * N_DRAWS + d] = relative_field_errors(field, truth)
    mean = errors.mean(axis=1)
    best = int(np.argmin(mean))
    n, m = sizes[best]
    table = [{"n": a, "planar": c, "error": round(float(e), 6)}
             for (a, c), e in zip(sizes, mean, strict=True)]
    curve = _curve_choice(fields, beads, usable, grid, shape, gram, seed=seed)
    kind = "lines" if curve is None else choose_kind(errors[best], curve["draw_errors"])
    if curve is not None:
        table.append({"n": 1, "planar": 1, "curve": curve["degree"],
                      "miss_factor": curve["miss_factor"],
                      "error": round(float(curve["error"]), 6),
                      "degree_errors": curve["errors"]})

    def model_of(j):
        if kind == "curve":
            return curve["left_out"][j]
        # its miss measured without the image left out, as an image's family measures
        # its own: the others' residuals about the whole family's lines would hold the
        # left-out image's direction, a smaller miss and a wider band
        return build_model(np.delete(fields, j, axis=0), n, grid, shape, gram, n_planar=m)

    band = spread_band(fields, beads, usable, model_of, seed=seed,
                       fits=curve["fits"] if kind == "curve" else None)
    out = {"kind": kind, "n_directions": 1 if kind == "curve" else n,
           "n_planar": 1 if kind == "curve" else m,
           "by": f"leaving each of {len(usable)} images out, identified from {N_CLICKS} of "
                 f"its beads ({N_DRAWS} draws)",
           "table": table, "band": band}
    if kind == "curve":
        out["curve"] = {"degree": curve["degree"], "thetas": curve["thetas"],
                        "miss_factor": curve["miss_factor"]}
    return out


def choose_kind(lines: np.ndarray, curve: np.ndarray) -> str:
    """``"lines"`` or ``"curve"`` from their left-out errors (N,), paired (the same
    images and draws; the lines' at the ``L`` and ``M`` of least mean error). The lines'
    ``L`` and ``M`` are the least of many sizes on these same draws, a minimum biased
    low by the draws' chance, so the lines replace the curve only where
    :func:`clearly_lower`."""
    return "lines" if clearly_lower(lines, curve) else "curve"


def clearly_lower(errors: np.ndarray, than: np.ndarray) -> bool:
    """Whether ``errors`` (N,) are lower than ``than`` (N,), paired (the same images and
    draws), by more than the standard error of their mean difference: a richer model
    replaces a simpler one only where the left-out images show it better beyond the
    draws' chance."""
    diff = np.asarray(than, np.float64) - np.asarray(errors, np.float64)
    if len(diff) < 2:
        return bool(diff.mean() > 0) if len(diff) else False
    return bool(diff.mean() > diff.std(ddof=1) / np.sqrt(len(diff)))


def _curve_choice(fields, beads, usable, grid, shape, gram, *, seed: int = 0
                  ) -> dict | None:
    """The curve's (:mod:`.curve`) left-out identifications as :func:`choose_dimensions`
    makes the lines': each image left out, the curve learnt from the others (from the
    whole family's ``theta``, :data:`CURVE_LEFT_OUT_ITERATIONS` steps; its miss that of
    the others' residuals about the whole family's curve, each left out), the image
    identified from the same draws of its beads (as an image is, weighing each bead by
    its noise and the miss). None below :data:`.curve.MIN_IMAGES` images besides the one
    left out.

    Each degree of :data:`.curve.DEGREES` is judged on the same draws (its ``theta``
    learnt from the lowest degree's, its fits started from that degree's); a higher
    degree replaces a lower one only where its mean error is lower by more than the
    standard error of their paired differences (:func:`clearly_lower`): a cubic learnt
    from ten images can swing where few of them lie, and is kept only where the
    family's own images show it better."""
    k = len(fields)
    if k - 1 < MIN_IMAGES:
        return None
    gy, gx = grid
    nodes = np.stack(np.meshgrid(gy, gx, indexing="ij"), axis=-1).reshape(-1, 2)
    white = whitener(gram).T
    degrees = [d for d in DEGREES if k - 1 >= d + 3]
    thetas, errors, left_out, fits = {}, {}, {}, {}
    for degree in degrees:
        # a higher degree's theta from the lower one's
        _, thetas[degree] = learn_thetas(fields, nodes, shape, gram, degree=degree,
                                         thetas=thetas.get(degrees[0]))
        residuals = curve_misses(fields, thetas[degree], nodes, shape, gram, degree=degree)

        def one(j, degree=degree, residuals=residuals):
            """Image ``j`` left out: the curve of the others, and its fits and errors
            at each draw and miss factor."""
            rest = np.arange(k) != j
            _, loo = learn_thetas(fields[rest], nodes, shape, gram, degree=degree,
                                  thetas=thetas[degree][rest],
                                  iterations=CURVE_LEFT_OUT_ITERATIONS)
            curve_j = build_curve(fields[rest], grid, shape, gram, thetas=loo,
                                  residuals=residuals[rest], degree=degree)
            b, out = beads[j], []
            for d, pick in enumerate(_draws(b, seed + j)):
                start = None if degree == degrees[0] else fits[degrees[0], 0, j, d].z
                for f, factor in enumerate(MISS_FACTORS):
                    # each weight's fit from the last one's: near it, one start does
                    _, (field, _, fit) = identify_any(
                        replace(curve_j, miss_factor=factor), b.coefficients[pick],
                        b.sd[pick], b.centers[pick], krige=False, spread=False,
                        start=start)
                    start = fit.z
                    out.append((d, f, fit, relative_field_error(field @ white,
                                                                fields[j] @ white)))
            return curve_j, out

        # the left-out images are independent: on the pool of threads, in order
        for j, (curve_j, out) in zip(usable, map_threads(one, usable), strict=True):
            left_out[degree, j] = curve_j
            for d, f, fit, error in out:
                fits[degree, f, j, d] = fit
                errors.setdefault((degree, f), []).append(error)
    best = {d: min((key for key in errors if key[0] == d),
                   key=lambda key: np.mean(errors[key])) for d in degrees}
    chosen = best[degrees[0]]
    for d in degrees[1:]:
        if clearly_lower(errors[best[d]], errors[chosen]):
            chosen = best[d]
    degree, f_best = chosen
    factor = MISS_FACTORS[f_best]
    return {"degree": int(degree), "error": float(np.mean(errors[chosen])),
            "draw_errors": np.asarray(errors[chosen]),
            "errors": {str(d): round(float(np.mean(errors[best[d]])), 6) for d in degrees},
            "miss_factor": factor, "thetas": thetas[degree].tolist(),
            "left_out": {j: replace(left_out[degree, j], miss_factor=factor)
                         for j in usable},
            "fits": {(j, d): fit for (g, f, j, d), fit in fits.items()
                     if (g, f) == chosen}}


def spread_band(fields: np.ndarray, beads: list[Beads | None], usable: list[int],
                model_of, *, seed: int = 0, fits: dict | None = None) -> dict:
    """The reported spread's calibration: for each left-out identification (as in
    :func:`choose_dimensions`, with the miss; ``model_of(j)`` the model of the fields
    but the ``j``-th, lines or a curve), the ratio of its actual error (against the
    image's own field) to the error its spread predicts (the rms over the field's
    central nodes, :attr:`~.coordinates.Model.central`, every third, of the PSF's
    relative posterior standard deviation); the quantiles :data:`BAND_QUANTILES` of the
    ratios scale a prediction into a band. ``fits``: a curve's fits of those draws, by
    ``(j, draw)`` (:func:`_curve_choice`'s: the fit does not depend on the miss)."""
    ratios = []
    for j in usable:
        model = model_of(j)
        # every third node of the field's central part: the same rms, a third the cost
        inside = np.flatnonzero(model.central)[::3]
        for d, pick in enumerate(_draws(beads[j], seed + j)):
            b = beads[j]
            if fits is not None and (j, d) in fits:
                fit = fits[j, d]
                lines = model.linearized(fit.z)
            else:
                lines, (_, _, fit) = identify_any(model, b.coefficients[pick], b.sd[pick],
                                                  b.centers[pick], krige=False,
                                                  spread=False)
            at = replace(lines, mean=lines.mean[inside],
                         directions=lines.directions[:, inside])
            add, miss_var = krige_miss(lines, fit, lines.nodes[inside])
            field = at.field(fit.z) + add
            spread = spread_at(at, fit, field, miss_var)
            predicted = float(np.sqrt(np.mean(spread ** 2)))
            actual = relative_field_error(field, fields[j][inside], lines.gram)
            if predicted > 0 and np.isfinite(actual):
                ratios.append(actual / predicted)
    if not ratios:
        return None
    lo, hi = np.quantile(ratios, BAND_QUANTILES)
    return {"low": float(lo), "high": float(hi), "median": float(np.median(ratios)),
            "n": len(ratios), "quantiles": list(BAND_QUANTILES)}


def family_model(family) -> Model | Curve:
    """The few-dimensional model of a family (:class:`~.result.OperatorFamily`), of the
    kind, ``L`` and ``M`` its learning chose (``metadata["dimensions"]``; a family
    without: all its directions, at most :data:`MAX_DIRECTIONS`, none planar): lines
    (:class:`~.coordinates.Model`) or a curve (:class:`~.curve.Curve`, rebuilt from its
    images' ``theta``). Built once per family."""
    cache = family._cache
    if "model" not in cache:
        fields = family_fields(family.space, family.gammas)
        dims = family.metadata.get("dimensions") or {}
        flat = family.basis.reshape(family.n_psf, -1)
        curve = dims.get("curve") if dims.get("kind") == "curve" else None
        if curve is not None:
            cache["model"] = build_curve(fields, family.grid, family.shape, flat @ flat.T,
                                         thetas=np.asarray(curve["thetas"], np.float64),
                                         degree=int(curve["degree"]),
                                         miss_factor=float(curve.get("miss_factor", 1.0)))
            return cache["model"]
        n = dims.get("n_directions")
        if n is None:
            n = min(MAX_DIRECTIONS, family.n_images - 1)
        cache["model"] = build_model(fields, int(n), family.grid, family.shape,
                                     flat @ flat.T, n_planar=int(dims.get("n_planar") or 0))
    return cache["model"]
