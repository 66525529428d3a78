"""The effects a simulated image can hold that the estimator is not told about
(:data:`EFFECTS`): illumination fall-off, fixed-pattern column offsets, hot pixels, a
compressive response, companions, bead sizes, background structure, drift and a
defocus gradient; their parameters are checked and drawn here.

The keys of ``effects`` of :func:`~.scene.simulate_beads` (``r`` below is
``truth.psf_radius``):

``"illumination": s`` (``0 < s < 1``) or ``(s, (row, col))``
    Non-uniform excitation ``I = 1 - s rho^2`` (``rho``: distance to
    the centre over the distance from the centre to the farthest
    corner, so ``I >= 1 - s``) multiplying the bead amplitudes (at
    each bead) and the smooth background. The centre is the field
    centre shifted by a random fraction (up to 20 %) of the field, or
    ``(row, col)`` pixels. Truth: ``illumination_centre``,
    ``illumination_map`` (H, W) float32, ``illumination_factors`` (M,).
``"row_offsets": sd``, ``"column_offsets": sd`` (ADU)
    Fixed-pattern offsets, normal with standard deviation ``sd``, per
    row / column, added to the ADU image after the noise. Truth:
    ``row_offset_values`` (H,), ``column_offset_values`` (W,).
``"hot_pixels": n`` (int), a fraction of the pixels (float < 1), or ``(n, (lo, hi))``
    Distinct random pixels with an extra dark signal uniform in
    [20 %, 100 %] of the median expected bead peak (ADU) (with
    ``(lo, hi)``: uniform in ``lo``-``hi`` times the brightest expected
    bead peak, e.g. ``(0.001, (1, 5))`` for an sCMOS without dark-frame
    correction; ``n`` a count or a fraction), added
    (noiseless) to the ADU image after the noise. Truth:
    ``hot_pixels`` (the count), ``hot_pixel_positions`` (n, 2) int
    ``(row, col)``, ``hot_pixel_values`` (n,) ADU.
``"saturation": level`` (ADU, above ``offset``, below the dtype max)
    The final image is clipped at ``level`` (rounded down for
    integer dtypes). Truth: ``saturation`` (the level),
    ``saturated_pixels`` (number of pixels at the level).
``"nonlinearity": c`` (``0 < c <= 0.5``)
    Compressive response ``e (1 - c e / e_ref)`` applied to the
    expected electrons before the shot noise, with ``e_ref`` the
    brightest expected pixel (a bead peak, background included), which
    loses the fraction ``c``; increasing up to ``e_ref / (2 c) >=
    e_ref`` and held constant beyond, so monotone. Truth:
    ``nonlinearity_reference`` (``e_ref``, electrons).
``"neighbours": f`` (``0 < f <= 1``) or a dict ``fraction``, ``distance_px``, ``amplitude``
    ``round(f M)`` random beads get a companion at a distance uniform
    in ``[0.6 r, 1.6 r]`` (or ``distance_px``) in a random direction,
    amplitude uniform in [0.3, 1] (or ``amplitude``) times the bead's
    (before illumination), same diameter,
    rendered with the PSF at its own position (the minimum
    separation is violated on purpose). ``truth.positions`` stays
    the primary beads. Truth: ``companion_positions`` (K, 2),
    ``companion_amplitudes`` (K,) photons, ``companion_of`` (K,)
    index of the primary bead.
``"bead_size": d`` or ``(d_min, d_max)`` (µm)
    Beads are uniform spheres of diameter ``d`` (or uniform in
    ``[d_min, d_max]``, with amplitude times ``d^3 / E[d^3]``): the
    optical PSF convolved with the projected sphere. Truth:
    ``bead_size`` ``(d_min, d_max)``, ``bead_diameters`` (M,) µm,
    ``companion_diameters`` (K,) with ``"neighbours"``.
``"drift": (dy, dx)`` (pixels)
    Linear sample motion during the exposure: each bead image is the
    PSF averaged along the segment from ``-(dy, dx) / 2`` to
    ``+(dy, dx) / 2`` about its (mid-exposure) position. Truth:
    ``drift``; :meth:`SimulationTruth.observed_psf_at` includes it.
``"background_structure": a`` (photons)
    Additive sum of Gaussian blobs of peak ``a``, sigma uniform in
    ``[0.3 r, 0.6 r]``, uniform centres, about one per ``(3 r)^2``
    pixels (structure at the scale of a bead patch that an order-2
    polynomial per patch does not describe). Not illuminated. Truth:
    ``background_structure_map`` (H, W) float32.

Invalid keys or values raise ValueError. The randomness of each effect
comes from its own child of the seeded generator
(:meth:`numpy.random.Generator.spawn`, one per key of ``EFFECTS`` in
that order), so effects draw nothing from the main stream: positions,
amplitude factors and smooth background equal those of
``effects=None``, each effect's realisation does not depend on the
other effects, and effects that do not change the expected photons
(offsets, hot pixels, saturation) leave the noise realisation
unchanged. ``effects=None`` (or ``{}``) is bit-identical to not
passing it.
"""

from __future__ import annotations

from collections.abc import Mapping
from math import ceil
from typing import Any

import numpy as np

from .optics import psf_stack

# ---------------------------------------------------------------------------
# Injectable effects (the ``effects`` argument of simulate_beads)
# ---------------------------------------------------------------------------

#: Effect keys, in the order of the child generators spawned for them.
EFFECTS = (
    "illumination",
    "row_offsets",
    "column_offsets",
    "hot_pixels",
    "saturation",
    "nonlinearity",
    "neighbours",
    "bead_size",
    "drift",
    "background_structure",
)
_ILLUMINATION_MAX_SHIFT = 0.2  # random shift of the illumination centre, fraction of the field
_HOT_PIXEL_RANGE = (0.2, 1.0)  # hot-pixel values, fraction of the typical bead peak (ADU)
_COMPANION_DISTANCE = (0.6, 1.6)  # companion distance, units of psf_radius
_COMPANION_AMPLITUDE = (0.3, 1.0)  # companion amplitude, fraction of its bead's
_BLOB_SIGMA = (0.3, 0.6)  # background-structure blob sigma, units of psf_radius
_BLOB_SPACING = 3.0  # one blob per (_BLOB_SPACING * psf_radius)^2 of field


def _scalar(
    effect: str,
    value: Any,
    low: float,
    high: float,
    *,
    open_low: bool = True,
    open_high: bool = False,
) -> float:
    """``value`` as a float in the interval ``(low, high]`` (bounds open/closed as told)."""
    try:
        if isinstance(value, bool):
            raise TypeError
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"effect {effect!r}: expected a number, got {value!r}") from None
    above = out > low if open_low else out >= low
    below = out < high if open_high else out <= high
    if not (np.isfinite(out) and above and below):
        lo, hi = "(" if open_low else "[", ")" if open_high else "]"
        raise ValueError(
            f"effect {effect!r}: value must lie in {lo}{low:g}, {high:g}{hi}, got {value!r}"
        )
    return out


def _pair(effect: str, value: Any) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"effect {effect!r}: expected two numbers, got {value!r}") from None
    if not (np.isfinite(a) and np.isfinite(b)):
        raise ValueError(f"effect {effect!r}: expected finite numbers, got {value!r}")
    return a, b


def check_effects(
    effects: Mapping[str, Any] | None,
    shape: tuple[int, int],
    dtype: np.dtype,
    offset: float,
) -> dict[str, Any]:
    """Validated, normalised effect parameters (see :func:`simulate_beads`)."""
    if effects is None:
        return {}
    if not isinstance(effects, Mapping):
        raise ValueError(f"effects must be a mapping or None, got {type(effects).__name__}")
    unknown = [k for k in effects if k not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect {unknown[0]!r}; valid effects: {', '.join(EFFECTS)}")
    out: dict[str, Any] = {}
    inf = np.inf
    for key, value in effects.items():
        if key == "illumination":
            out[key] = _illumination(key, value)
        elif key in ("row_offsets", "column_offsets", "background_structure"):
            out[key] = _scalar(key, value, 0.0, inf, open_low=False, open_high=True)
        elif key == "hot_pixels":
            out[key] = _hot_pixels(key, value, shape)
        elif key == "saturation":
            top = np.iinfo(dtype).max if np.issubdtype(dtype, np.integer) else inf
            level = _scalar(key, value, offset, top, open_high=True)
            out[key] = float(np.floor(level)) if np.issubdtype(dtype, np.integer) else level
        elif key == "nonlinearity":
            out[key] = _scalar(key, value, 0.0, 0.5)
        elif key == "neighbours":
            out[key] = _neighbours(key, value)
        elif key == "bead_size":
            low, high = (value, value) if np.isscalar(value) else _pair(key, value)
            low = _scalar(key, low, 0.0, inf, open_low=False, open_high=True)
            high = _scalar(key, high, 0.0, inf, open_low=False, open_high=True)
            if low > high:
                raise ValueError(f"effect {key!r}: need d_min <= d_max, got {value!r}")
            out[key] = (low, high)
        elif key == "drift":
            out[key] = _pair(key, value)
    return out


def _illumination(key: str, value: Any) -> tuple[float, tuple[float, float] | None]:
    """``s`` or ``(s, (row, col))``: the fall-off's strength and its centre (None: the
    image's)."""
    if np.isscalar(value):
        return _scalar(key, value, 0.0, 1.0, open_high=True), None
    try:
        strength, centre = value
    except (TypeError, ValueError):
        raise ValueError(
            f"effect {key!r}: expected s or (s, (row, col)), got {value!r}"
        ) from None
    return _scalar(key, strength, 0.0, 1.0, open_high=True), _pair(key, centre)


def _hot_pixels(key: str, value: Any, shape: tuple[int, int]):
    """A count or a fraction of the pixels, optionally with the range ``(low, high)`` of
    their factors: the count, or ``(count, (low, high))``."""
    factors = None
    if isinstance(value, (tuple, list)):  # (count or fraction, (low, high))
        try:
            value, factors = value
        except (TypeError, ValueError):
            raise ValueError(f"effect {key!r}: expected n, a fraction, or (n or "
                             f"fraction, (low, high)), got {value!r}") from None
        factors = _pair(key, factors)
        if not 0 < factors[0] <= factors[1]:
            raise ValueError(f"effect {key!r}: need 0 < low <= high, got {factors}")
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        count = int(value)
    else:
        count = round(_scalar(key, value, 0.0, 1.0, open_high=True) * shape[0] * shape[1])
    if not 0 <= count <= shape[0] * shape[1]:
        raise ValueError(
            f"effect {key!r}: count must lie in [0, {shape[0] * shape[1]}], got {value!r}"
        )
    return count if factors is None else (count, factors)


def _neighbours(key: str, value: Any):
    """A fraction of the beads given a companion, or a dict of ``fraction`` and optionally
    ``distance_px`` and ``amplitude`` (each a range ``(low, high)``)."""
    if not isinstance(value, dict):
        return _scalar(key, value, 0.0, 1.0)
    unknown = sorted(set(value) - {"fraction", "distance_px", "amplitude"})
    if unknown or "fraction" not in value:
        raise ValueError(f"effect {key!r}: a dict needs 'fraction' and may hold "
                         f"'distance_px', 'amplitude'; got keys {sorted(value)}")
    dist = value.get("distance_px")
    if dist is not None:
        dist = _pair(key, dist)
        if not 0 < dist[0] <= dist[1]:
            raise ValueError(f"effect {key!r}: need 0 < distance_px low <= high, "
                             f"got {value['distance_px']!r}")
    amp = _pair(key, value.get("amplitude", _COMPANION_AMPLITUDE))
    if not 0 < amp[0] <= amp[1]:
        raise ValueError(f"effect {key!r}: need 0 < amplitude low <= high, got "
                         f"{value.get('amplitude')!r}")
    return {"fraction": _scalar(key, value["fraction"], 0.0, 1.0),
            "distance_px": dist, "amplitude": amp}


def illumination_map(
    rng: np.random.Generator, shape: tuple[int, int], strength: float, centre
) -> tuple[np.ndarray, Any]:
    """Centre of ``I = 1 - s rho^2`` and a function evaluating it at ``(y, x)``.

    ``rho`` is the distance to the centre divided by the distance from the
    centre to the farthest image corner (the half-diagonal for a centred
    field), so ``1 - s <= I <= 1``. Without an explicit centre, the field
    centre is shifted by a uniform random fraction (up to 20 %) of the field.
    """
    if centre is None:
        shift = rng.uniform(-_ILLUMINATION_MAX_SHIFT, _ILLUMINATION_MAX_SHIFT, 2)
        centre = (np.array(shape) - 1) / 2.0 + shift * np.array(shape)
    centre = np.asarray(centre, float)
    corners = np.array([[0, 0], [0, shape[1] - 1], [shape[0] - 1, 0], [shape[0] - 1, shape[1] - 1]])
    scale = max(float(np.hypot(*(corners - centre).T).max()), 1.0)

    def evaluate(y, x):
        rho2 = (np.asarray(y, float) - centre[0]) ** 2 + (np.asarray(x, float) - centre[1]) ** 2
        return 1.0 - strength * rho2 / scale**2

    return centre, evaluate


def fixed_pattern(rng: np.random.Generator, n: int, sd: float) -> np.ndarray:
    """Per-row (or per-column) offsets, ADU, normal with standard deviation ``sd``."""
    return rng.normal(0.0, sd, n)


def hot_pixels(
    rng: np.random.Generator, shape: tuple[int, int], count: int, peak_adu: float,
    factors: tuple[float, float] = _HOT_PIXEL_RANGE,
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` distinct pixels ``(row, col)`` with values uniform in ``factors`` times
    the peak."""
    flat = rng.choice(shape[0] * shape[1], size=count, replace=False)
    where = np.stack(np.unravel_index(np.sort(flat), shape), axis=1)
    values = peak_adu * rng.uniform(*factors, size=count)
    return where, values


def nonlinear(electrons: np.ndarray, c: float, e_ref: float) -> np.ndarray:
    """Compressive response ``e (1 - c e / e_ref)``, monotone.

    Increasing for ``e <= e_ref / (2 c)`` (which holds up to ``e_ref`` since
    ``c <= 0.5``); held at its maximum ``e_ref / (4 c)`` beyond.
    """
    e = np.minimum(electrons, e_ref / (2.0 * c))
    return e * (1.0 - c * e / e_ref)


def companions(
    rng: np.random.Generator, positions: np.ndarray, spec, radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Owner index, position and relative amplitude of companion beads.

    ``spec`` is a fraction ``f`` or a dict (``fraction``, ``distance_px``,
    ``amplitude``). ``round(f * M)`` distinct beads each get one companion at a
    distance uniform in ``[0.6, 1.6] * radius`` (or ``distance_px``) in a uniform
    direction, with an amplitude factor uniform in ``[0.3, 1]`` (or ``amplitude``).
    """
    if isinstance(spec, dict):
        fraction, dist, amp = spec["fraction"], spec["distance_px"], spec["amplitude"]
    else:
        fraction, dist, amp = spec, None, _COMPANION_AMPLITUDE
    dist = dist if dist is not None else tuple(radius * d for d in _COMPANION_DISTANCE)
    count = round(fraction * len(positions))
    owners = np.sort(rng.choice(len(positions), size=count, replace=False))
    distance = rng.uniform(*dist, size=count)
    angle = rng.uniform(0.0, 2.0 * np.pi, size=count)
    factor = rng.uniform(*amp, size=count)
    where = positions[owners] + distance[:, None] * np.stack([np.sin(angle), np.cos(angle)], 1)
    return owners, where, factor


def bead_diameters(
    rng: np.random.Generator, n: int, d_range: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Diameters (µm) uniform in ``d_range`` and brightness factors ``d^3 / E[d^3]``."""
    low, high = d_range
    diameters = rng.uniform(low, high, size=n) if high > low else np.full(n, low)
    mean_cube = (high**4 - low**4) / (4.0 * (high - low)) if high > low else low**3
    factors = diameters**3 / mean_cube if mean_cube > 0 else np.ones(n)
    return diameters, factors


def background_structure(
    rng: np.random.Generator, shape: tuple[int, int], peak: float, radius: float
) -> np.ndarray:
    """Sum of Gaussian blobs of peak ``peak`` photons, sigma in ``[0.3, 0.6] * radius``.

    Uniform centres over the field, about one per ``(3 radius)^2`` pixels:
    structure at the scale of a bead patch, wider than the PSF core. On
    ``2 r x 2 r`` patches an order-2 polynomial leaves about half of its rms
    (wider blobs, sigma up to ``r``, are mostly absorbed: a third).
    """
    count = max(1, round(shape[0] * shape[1] / (_BLOB_SPACING * radius) ** 2))
    centres = rng.uniform((0.0, 0.0), (shape[0] - 1.0, shape[1] - 1.0), size=(count, 2))
    sigmas = radius * rng.uniform(*_BLOB_SIGMA, size=count)
    out = np.zeros(shape)
    for (cy, cx), sigma in zip(centres, sigmas, strict=True):
        half = ceil(4.0 * sigma)
        y0, y1 = max(int(cy) - half, 0), min(int(cy) + half + 1, shape[0])
        x0, x1 = max(int(cx) - half, 0), min(int(cx) + half + 1, shape[1])
        gy = np.exp(-0.5 * ((np.arange(y0, y1) - cy) / sigma) ** 2)
        gx = np.exp(-0.5 * ((np.arange(x0, x1) - cx) / sigma) ** 2)
        out[y0:y1, x0:x1] += peak * np.outer(gy, gx)
    return out.astype(np.float32)


def typical_peak(
    amplitudes: np.ndarray, peaks: np.ndarray, amp_range, aberrations, optics, shape
) -> float:
    """Median expected bead peak, photons (mean amplitude x PSF peak at the centre if no bead)."""
    if len(amplitudes):
        return float(np.median(amplitudes * peaks))
    centre = aberrations.coefficient_matrix((shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0, shape)
    psf = psf_stack(aberrations.noll_indices, centre[None], np.zeros((1, 2)), optics, 9)
    return float(np.mean(amp_range) * psf.max())
