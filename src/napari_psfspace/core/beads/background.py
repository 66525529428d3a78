"""Per-patch background removal by a low-order polynomial (paper, Appendix B).

Two ways, both linear least squares:

- :func:`fit_background` (the paper's): a polynomial of order 2 (monomials 1, x, y, xy,
  x², y²) fitted to the patch's pixels farther than ``r`` from its centre. One
  pseudo-inverse serves every patch, so it costs one matrix product for any number of
  beads. Those pixels still hold the PSF's wings (a tenth of its light lies beyond the
  radius that holds nine tenths), and the quadratic terms carry the wings' fall-off into
  the core: the background is biased under the bead.
- :func:`ring_background` (the estimator's): a plane fitted on a wider ring, from the
  window's edge ``r_ext`` to :data:`RING_OUTER` radii, on the image's own pixels (no
  re-sampling), pixels far above the plane left out as another source's light, and the
  plane evaluated on the patch's sub-pixel grid. Farther out the wings are fainter, and a
  plane cannot bend under the core. The bead's own wings still reach the ring (one to two
  per cent of an in-focus PSF's light lies between 1.2 and 1.6 radii): they are fitted
  with the plane, as a fall-off with the cube of the distance (the envelope of an
  aperture's diffraction) scaled by the bead's light, its scale one for the image.

A camera whose noise is far below one of its steps (a few photons of background at 20
photons an ADU, say) rounds most of a ring to one level: the level read there is the
rounding's, off the true one by up to half a step, and the wings' faint fall-off is
rounded away. Such an image (:func:`rounding_noise` under :data:`SUBSTEP_SD` of a step)
keeps the plane alone.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtri

from .centering import gather_windows
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


#: Outer radius of the ring :func:`ring_background` fits its plane on, in PSF radii.
RING_OUTER = 1.6

#: Pixels of the ring more than this many robust standard deviations from the plane are
#: left out of the next fit: light of a source the neighbour model missed, or took out
#: too much of.
RING_CLIP = 3.0

#: Fits of the plane after the first, each without the pixels :data:`RING_CLIP` leaves out.
RING_PASSES = 2

#: Fit the beads' own wings on their rings with the planes (:func:`_own_wings`).
OWN_WINGS = True

#: Power of the radial fall-off of a PSF's own light beyond its core (an aperture's
#: diffraction: the Airy envelope falls as the cube of the distance).
WING_POWER = 3.0

#: The wings' scale taken is its estimate less this many standard errors (at least 0): a
#: lower confidence bound, so that an image whose beads disagree keeps the plane alone.
WING_Z = 2.0

#: An image whose rings' noise (:func:`rounding_noise`) is under this many of its value
#: steps keeps the plane alone. Rounding a level with Gaussian noise of ``sigma`` steps
#: moves its mean by up to ``exp(-2 pi**2 sigma**2) / pi`` of a step: 0.09 at a quarter
#: step (0.002 at half a step), as much as the wings' own level on the ring, which the
#: fit could then not tell from the rounding.
SUBSTEP_SD = 0.25


def ring_background(image: np.ndarray, centers: np.ndarray, r: float, r_ext: float,
                    size: int, *, outer: float | None = None, neighbours=None
                    ) -> np.ndarray:
    """A plane fitted to each bead's ring of background, evaluated on its patch.

    Parameters
    ----------
    image : ndarray of shape (M, N)
    centers : ndarray of shape (K, 2)
        Sub-pixel centres (row, column), pixels.
    r, r_ext : float
        PSF and window radii, pixels: the ring starts beyond ``r_ext``.
    size : int
        Odd patch size: pixel ``(i, j)`` of a patch lies at ``center - size // 2 + (i,
        j)`` (as :func:`~napari_psfspace.core.beads.patches.resample_patches`).
    outer : float, optional
        Half-width of the square the ring is cut from, pixels (default
        ``RING_OUTER * r``, at least one pixel beyond the patch).
    neighbours : NeighbourLight, optional
        Other detections' modelled light, taken out of the ring first.

    Notes
    -----
    Each bead's own light on its ring, ``c F_k (r_ext / rho)**3`` at distance ``rho`` (``F_k``
    its light within ``r_ext`` above its plane), is fitted with the planes: one scale
    ``c >= 0`` for the image, by least squares with the planes eliminated, less
    :data:`WING_Z` standard errors from the beads' scatter. A plane alone takes the wings'
    mean level on the ring for background and removes it from every pixel of the patch.
    A PSF without wings there, or beads that disagree (a background that curves about
    them reads as a wing of either sign), get ``c = 0``: the plane alone.

    Returns
    -------
    ndarray of shape (K, size, size), float64
        Each patch's background. A ring cut by the image's edge is fitted on its pixels
        inside the image; with fewer than six of them, their median level.
    """
    centers = np.asarray(centers, np.float64).reshape(-1, 2)
    half = int(size) // 2
    h = max(int(np.ceil(RING_OUTER * r if outer is None else outer)), half + 1)
    d = np.arange(-h, h + 1, dtype=np.float64)
    wins = gather_windows(image, centers, h).astype(np.float64).reshape(len(centers), -1)
    base = np.round(centers)
    rows, cols = base[:, :1] + d, base[:, 1:] + d
    seen = (((rows >= 0) & (rows < image.shape[0]))[:, :, None]
            & ((cols >= 0) & (cols < image.shape[1]))[:, None, :]).reshape(len(centers), -1)
    ring = np.hypot(d[:, None], d[None, :]).ravel() > r_ext
    yy, xx = np.meshgrid(d / h, d / h, indexing="ij")
    design = np.stack([np.ones(yy.size), xx.ravel(), yy.ravel()], axis=1)[ring]
    vals = wins[:, ring]
    if neighbours is not None:
        points = np.stack([yy.ravel(), xx.ravel()], axis=1)[ring] * h
        for k in range(len(centers)):
            vals[k] -= neighbours.around(centers[k], base[k] + points)
    use = seen[:, ring].astype(np.float64)
    coef = _planes(design, vals, use)
    seen_any = use.any(axis=1)
    step = value_step(image)
    frac = centers - base
    full = np.stack([np.ones(yy.size), xx.ravel(), yy.ravel()], axis=1)
    wings = OWN_WINGS and not (
        step > 0 and rounding_noise(wins[:, ring], use > 0, step) < SUBSTEP_SD * step)
    if wings:  # (r_ext / rho)**WING_POWER on each bead's ring, rho from its centre
        dist = np.hypot((d[None, :, None] - frac[:, :1, None]),
                        (d[None, None, :] - frac[:, 1:, None])).reshape(len(centers), -1)
        falloff = (r_ext / dist[:, ring]) ** WING_POWER
    wing = np.zeros_like(vals)
    keep = use > 0
    for _ in range(RING_PASSES):  # fitted again without the pixels far from the plane
        if wings:
            wing = _own_wings(wins, seen, coef, full, ring, falloff, vals, use * keep)
            coef = _planes(design, vals - wing, use * keep)
        res = np.where(use > 0, vals - wing - coef @ design.T, np.nan)
        res[~seen_any] = 0.0
        med = np.nanmedian(res, axis=1, keepdims=True)
        # a quantised image's background can hold one level in most of its pixels:
        # its MAD is then 0, and every pixel a level away would be left out
        scale = np.maximum(1.4826 * np.nanmedian(np.abs(res - med), axis=1, keepdims=True),
                           step)
        keep = np.abs(res - med) <= RING_CLIP * scale  # NaN (not seen): False
        coef = _planes(design, vals - wing, use * keep)
    off = (np.arange(size, dtype=np.float64) - half)
    py = (off[None, :] + frac[:, :1]) / h  # (K, size)
    px = (off[None, :] + frac[:, 1:]) / h
    return (coef[:, 0, None, None] + coef[:, 1, None, None] * px[:, None, :]
            + coef[:, 2, None, None] * py[:, :, None])


def _own_wings(wins, seen, coef, full, ring, falloff, vals, use):
    """Each bead's own light on its ring (K, n): ``c F_k (r_ext / rho)**WING_POWER``, one
    ``c >= 0`` for the image, fitted by least squares with each bead's plane (the planes
    eliminated) less :data:`WING_Z` standard errors, ``F_k`` the bead's light within
    ``r_ext`` above its plane."""
    inside = ~ring
    flux = np.sum(np.where(seen[:, inside], wins[:, inside] - coef @ full[inside].T, 0.0),
                  axis=1)
    shape = np.maximum(flux, 0.0)[:, None] * falloff
    design = full[ring]
    a = use * (shape - _planes(design, shape, use) @ design.T)
    b = use * (vals - _planes(design, vals, use) @ design.T)
    aa, ab = np.sum(a * a, axis=1), np.sum(a * b, axis=1)
    den = float(aa.sum())
    if den <= 0 or np.count_nonzero(aa > 0) < 2:
        return np.zeros_like(vals)
    c = float(ab.sum()) / den
    # the scale's standard error from the beads' scatter about it (each bead's residual
    # times its regressor, a sandwich estimate): a background that curves about a bead
    # reads as a wing of either sign there; only the scale the beads agree on is taken
    se = float(np.sqrt(np.sum((ab - c * aa) ** 2))) / den
    c = max(c - WING_Z * se, 0.0)
    return c * shape


def rounding_noise(values: np.ndarray, use: np.ndarray, step: float) -> float:
    """The noise's standard deviation on rings of a quantised image, in image units, read
    from how often a value leaves its ring's level.

    Parameters
    ----------
    values : ndarray of shape (K, n)
        Each ring's pixels as recorded (on the image's lattice of levels).
    use : ndarray of shape (K, n), bool
        The pixels in the image.
    step : float
        The lattice's step (:func:`value_step`), > 0.

    Returns
    -------
    float
        ``step / (a + b)``, where ``a`` and ``b`` are the normal quantiles of the shares
        ``p_up`` and ``p_down`` of pixels more than half a step above and below their ring's
        median (pooled over the rings; each at least half a pixel's share, at most a half).
        A Gaussian of sd ``sigma`` about a level ``delta`` off its step's centre gives
        ``(step / 2 - delta) / sigma = a`` and ``(step / 2 + delta) / sigma = b``. A ring's
        tilt, structure and wings add to both shares: an upper estimate.
    """
    vals = np.where(use, np.asarray(values, np.float64), np.nan)
    rows = use.any(axis=1)
    if not rows.any():
        return float("inf")
    vals = vals[rows]
    level = np.nanmedian(vals, axis=1, keepdims=True)
    n = int(np.count_nonzero(use[rows]))
    lo, hi = 0.5 / n, 0.5
    p_up = min(max(np.count_nonzero(vals > level + step / 2) / n, lo), hi)
    p_down = min(max(np.count_nonzero(vals < level - step / 2) / n, lo), hi)
    a, b = -ndtri(p_up), -ndtri(p_down)  # upper-tail normal quantiles
    return float(step / (a + b)) if a + b > 0 else float("inf")


def value_step(image: np.ndarray, *, sample: int = 65536) -> float:
    """The step between an image's levels: the least difference between its distinct
    values when every value lies on that lattice (a camera's ADU, or a scaled copy of
    them) of at most 2**20 levels, else 0. Read from at most ``sample`` pixels spread
    over the image."""
    flat = np.asarray(image).ravel()
    vals = np.unique(flat[::max(1, flat.size // sample)].astype(np.float64))
    if len(vals) < 2:
        return 0.0
    step = float(np.min(np.diff(vals)))
    levels = (vals - vals[0]) / step
    if levels[-1] > 2**20 or not np.allclose(levels, np.round(levels), atol=1e-3):
        return 0.0  # more levels than a camera has, or off any lattice: continuous
    return step


def _planes(design: np.ndarray, vals: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Weighted least-squares planes (K, 3) of ``vals`` (K, n) on ``design`` (n, 3) with
    0/1 weights ``use`` (K, n); a bead with fewer than six pixels in use gets its median
    level (no slope)."""
    m = design.shape[1]
    # one matrix product each (an einsum over three operands loops in C, slower by far)
    gram = (use @ (design[:, :, None] * design[:, None, :]).reshape(len(design), m * m)
            ).reshape(-1, m, m)
    rhs = (use * vals) @ design
    enough = use.sum(axis=1) >= 2 * design.shape[1]
    coef = np.zeros((len(vals), design.shape[1]))
    if enough.any():
        coef[enough] = np.linalg.solve(gram[enough], rhs[enough][:, :, None])[:, :, 0]
    for k in np.flatnonzero(~enough):
        u = use[k] > 0
        coef[k, 0] = float(np.median(vals[k, u])) if u.any() else 0.0
    return coef
