"""A seeded set of realistic bead scenes, so that thresholds are never tuned on one.

:func:`random_scene` draws the microscope, the slide and the camera from wide ranges
(:data:`RANGES`) and renders the image with
:func:`~napari_psfspace.core.simulation.scene.simulate_beads`:
pixel size, NA, emission wavelength, aberrations (presets or a random field), bead
count, log-normal bead brightness spread, background, camera gain, offset, read noise
and bit depth. Any parameter can be fixed, or given its own range, by keyword, e.g. the
low-count 8-bit set of the detection bench::

    image, truth, params = random_scene(3, shape=(512, 512), bits=8, background=(1, 5),
                                        peak_adu=(50, 250))

Ranges are drawn uniformly, log-uniformly for the scale parameters
(:data:`LOG_SCALE`); a tuple of strings or a list is a set of choices.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .aberrations import FieldAberrations
from .optics import PSF_ENERGY_FRACTION, Optics, field_psf_radius, simulate_psf
from .scene import simulate_beads
from .truth import SimulationTruth

#: Default range of every scene parameter (units in :func:`random_scene`).
RANGES: dict[str, Any] = {
    "pixel_size": (0.043, 0.160),
    "na": (0.7, 1.49),
    "wavelength": (0.45, 0.70),
    "aberrations": ["none", "moderate", "strong", "random"],
    "random_strength": (0.02, 0.12),
    "n_beads": (20, 600),
    "spread": (0.1, 1.0),
    "background": (1.0, 500.0),
    "background_variation": (0.0, 0.5),
    "peak_photons": (30.0, 3e4),
    "peak_adu": None,
    "gain": None,
    "offset": (0.0, 100.0),
    "read_noise": (0.5, 3.0),
    "bits": [8, 12, 16],
    "min_separation": 2.5,
    "fill": (0.3, 0.95),
    "per_bead": False,
}
#: The 8-bit low-count set: background 1-5 photons, bead peaks 50-250 ADU drawn per
#: bead, from photon-limited cameras (gain up to 2 ADU/e-) to 8-bit exports of deeper
#: ones (gain down to 0.01 ADU/e-, the background's noise far below one ADU); beads may
#: lie as close as one PSF radius. Use as ``random_scene(seed, **LOW_COUNT_8BIT)``.
LOW_COUNT_8BIT: dict[str, Any] = {
    "shape": (512, 512), "bits": 8, "background": (1.0, 5.0), "peak_adu": (50, 250),
    "per_bead": True, "n_beads": (20, 80), "min_separation": 1.0, "gain": (0.01, 2.0)}
#: Parameters drawn log-uniformly from their range.
LOG_SCALE = frozenset({"background", "peak_photons", "peak_adu", "gain", "n_beads"})
#: The gain (ADU per photo-electron) of a scene whose gain follows from ``peak_adu`` and
#: no gain range is given.
PEAK_ADU_GAIN = (0.1, 2.0)


def _draw(rng: np.random.Generator, name: str, spec) -> Any:
    if spec is None:
        return None
    if isinstance(spec, list):
        return spec[int(rng.integers(len(spec)))]
    if isinstance(spec, tuple) and len(spec) == 2 and not isinstance(spec[0], str):
        lo, hi = float(spec[0]), float(spec[1])
        if hi < lo:
            raise ValueError(f"scene parameter `{name}`: range {spec!r} has high < low.")
        if name in LOG_SCALE and lo > 0:
            return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        return float(rng.uniform(lo, hi))
    return spec


def random_scene(
    seed: int,
    *,
    shape: tuple[int, int] = (512, 512),
    effects: dict | None = None,
    optics_type: type[Optics] = Optics,
    **overrides,
) -> tuple[np.ndarray, SimulationTruth, dict]:
    """Draw one bead scene of the set and render it.

    Parameters
    ----------
    seed : int
        Seed of everything (parameters, bead positions and brightness, noise).
    shape : tuple of int
        Image shape (rows, columns).
    effects : dict, optional
        Effects injected into the scene, as ``effects`` of
        :func:`~napari_psfspace.core.simulation.scene.simulate_beads`
        (e.g. ``{"drift": (dy, dx)}``
        for a smear during the exposure), and ``"defocus_gradient"``: defocus (Zernike
        4) growing linearly across the field by this many waves rms from side to side
        (random direction; or ``(span, angle_deg)``); they do not change the draw of the
        scene.
    optics_type : type
        The optics' class: :class:`~.optics.Optics`, or a subclass whose PSFs come from
        other optics code (``bench/independent.py``), the draw of the scene unchanged.
    **overrides
        Any key of :data:`RANGES`, fixed (a number or string) or as a ``(low, high)``
        range, or a list of choices:

        ``pixel_size`` (µm), ``na``, ``wavelength`` (emission, µm),
        ``aberrations`` ("none", "moderate", "strong" or "random", a random low-degree
        field whose coefficients have rms ``random_strength`` waves),
        ``n_beads``, ``spread`` (sigma of the log-normal bead brightness),
        ``background`` (photons per pixel, mean), ``background_variation`` (the smooth
        background spans ``background (1 -+ variation)``), ``peak_photons`` (median bead peak,
        photons in the brightest pixel), ``peak_adu`` (instead of ``peak_photons``:
        the median peak in ADU above the offset; ``gain`` is then drawn from
        :data:`PEAK_ADU_GAIN` unless given), ``gain`` (ADU per photo-electron; default:
        the brightest beads fill ``fill`` of the full scale, between 0.05 and 5),
        ``offset`` (ADU), ``read_noise`` (electrons), ``bits`` (8, 12 or 16; 12-bit
        images are uint16 clipped at 4095), ``min_separation`` (bead centres at least
        this many PSF radii apart), ``per_bead`` (True: every bead's peak is drawn
        log-uniformly from the ``peak_adu`` or ``peak_photons`` range, and ``spread``
        is not used; default False: the range gives the scene's median peak).

    Returns
    -------
    image : ndarray of shape ``shape``, uint8 or uint16
    truth : SimulationTruth
    params : dict
        The drawn parameters (JSON-ready), with ``full_scale`` and ``psf_radius``.
    """
    unknown = sorted(set(overrides) - set(RANGES))
    if unknown:
        raise ValueError(f"Unknown scene parameter(s) {unknown}; known: {sorted(RANGES)}.")
    spec = {**RANGES, **overrides}
    rng = np.random.default_rng(seed)
    p, full = _draw_parameters(spec, rng)
    optics = optics_type(na=p["na"], wavelength=p["wavelength"], pixel_size=p["pixel_size"])
    if p["aberrations"] == "random":
        aberrations = FieldAberrations.random(p["random_strength"], seed=rng)
    else:
        aberrations = FieldAberrations.preset(p["aberrations"])
    effects = dict(effects or {})
    gradient = effects.pop("defocus_gradient", None)
    layout = aberrations  # the bead layout follows the field without the gradient
    if gradient is not None:
        aberrations, p["defocus_gradient"] = _add_defocus_gradient(aberrations, gradient,
                                                                   seed)
    centre = aberrations.coefficients((shape[0] - 1) / 2, (shape[1] - 1) / 2, shape)
    peak_fraction = float(simulate_psf(centre, optics=optics, size=15).max())

    photons = _bead_photons(spec, rng, p, full, peak_fraction)
    dtype = np.uint8 if p["bits"] == 8 else np.uint16
    r = field_psf_radius(layout, optics, shape, PSF_ENERGY_FRACTION)
    # dart throwing fills about half of a hexagonal packing: never ask for more
    sep = p["min_separation"] * r
    room = (shape[0] - 2 * r) * (shape[1] - 2 * r) / (np.sqrt(3) / 2 * max(sep, 1.0) ** 2)
    p["n_beads"] = int(min(p["n_beads"], max(1, 0.4 * room)))
    photons = photons[:p["n_beads"]]
    bg, var = p["background"], p["background_variation"]
    image, truth = simulate_beads(
        shape, p["n_beads"], aberrations=aberrations, optics=optics,
        background=(bg * (1 - var), bg * (1 + var)), gain=p["gain"], offset=p["offset"],
        read_noise=p["read_noise"], dtype=dtype, seed=rng,
        min_separation=p["min_separation"] * r, border=r, bead_photons=photons,
        effects=effects or None)
    if p["bits"] == 12:
        image = np.minimum(image, full).astype(dtype)
    p.update(full_scale=full, psf_radius=int(truth.psf_radius), peak_fraction=peak_fraction,
             aberrations=p["aberrations"] if isinstance(p["aberrations"], str) else "custom")
    return image, truth, {k: (float(v) if isinstance(v, np.floating) else v)
                          for k, v in p.items()}


def _draw_parameters(spec, rng):
    """The scene's optics, field, beads, background and camera drawn from ``spec`` in a
    fixed order, and its full scale."""
    p: dict[str, Any] = {}
    for name in ("pixel_size", "na", "wavelength", "aberrations", "random_strength",
                 "n_beads", "spread", "background", "background_variation", "bits",
                 "offset", "read_noise", "min_separation", "fill"):
        p[name] = _draw(rng, name, spec[name])
    p["n_beads"] = int(round(p["n_beads"]))
    p["bits"] = int(p["bits"])
    if p["bits"] not in (8, 12, 16):
        raise ValueError(f"scene parameter `bits` must be 8, 12 or 16, got {p['bits']!r}.")
    full = 2 ** p["bits"] - 1
    if p["bits"] == 8:
        p["offset"] = min(p["offset"], 10.0)
    return p, full


def _bead_photons(spec, rng, p, full, peak_fraction):
    """Each bead's photons and the camera's gain: the median peak drawn in photons or in ADU
    (the gain then drawn too, else set so that the brightest beads fill ``fill`` of the full
    scale), the beads' peaks log-normal about it (or each drawn from the range,
    ``per_bead``); ``p`` is completed in place."""
    p["per_bead"] = bool(spec["per_bead"])
    if p["per_bead"]:
        p["spread"] = 0.0
    bright = float(np.exp(2 * p["spread"]))  # a bead two sd above the median
    by_adu = spec["peak_adu"] is not None
    key = "peak_adu" if by_adu else "peak_photons"
    p[key] = _draw(rng, key, spec[key])
    if by_adu:
        gain = _draw(rng, "gain", spec["gain"] if spec["gain"] is not None else PEAK_ADU_GAIN)
        p["peak_photons"] = p["peak_adu"] / gain
    else:
        gain = _draw(rng, "gain", spec["gain"])
        if gain is None:
            top = (float(spec[key][1]) if p["per_bead"] and isinstance(spec[key], tuple)
                   else p["peak_photons"] * bright)
            gain = float(np.clip(p["fill"] * (full - p["offset"]) / (top + p["background"]),
                                 0.05, 5.0))
        p["peak_adu"] = gain * p["peak_photons"]
    p["gain"] = gain
    if p["per_bead"] and isinstance(spec[key], tuple):
        lo, hi = np.log(float(spec[key][0])), np.log(float(spec[key][1]))
        peaks = np.exp(rng.uniform(lo, hi, p["n_beads"]))
        peaks = peaks / gain if by_adu else peaks
    else:
        peaks = p["peak_photons"] * np.exp(p["spread"] * rng.standard_normal(p["n_beads"]))
    photons = peaks / peak_fraction
    return photons


def _add_defocus_gradient(aberrations: FieldAberrations, spec, seed: int):
    """Defocus (Noll 4) growing linearly across the field.

    ``spec``: the span in waves rms over the field, max - min (a random
    direction, drawn from its own generator so that the scene's draw is unchanged), or
    ``(span, angle_deg)`` (0: along columns, x).
    """
    if np.isscalar(spec):
        span = float(spec)
        angle = float(np.random.default_rng([seed, 4]).uniform(0.0, 360.0))
    else:
        span, angle = (float(v) for v in spec)
    if not np.isfinite(span) or not np.isfinite(angle):
        raise ValueError(f"effect 'defocus_gradient': expected a finite span (waves) or "
                         f"(span, angle_deg), got {spec!r}")
    # ``u cos + v sin`` spans [-(|cos| + |sin|), |cos| + |sin|] over the field (the
    # corners): scale so that the defocus spans ``span`` over the field (max - min)
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    half = span / 2.0 / (abs(c) + abs(s))
    terms = {j: list(v) for j, v in aberrations.terms.items()}
    z4 = terms.get(4, [0.0] * 6)
    z4[1] += half * c
    z4[2] += half * s
    terms[4] = z4
    return FieldAberrations(terms), {"span_waves": span, "angle_deg": angle}


def isolated(positions: np.ndarray, radius: float) -> np.ndarray:
    """True for positions with no other position within ``2 radius``, shape (M,)."""
    from scipy.spatial import cKDTree

    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    if len(pos) < 2:
        return np.ones(len(pos), bool)
    dist, _ = cKDTree(pos).query(pos, k=2)
    return dist[:, 1] >= 2 * radius


def match(found: np.ndarray, truth: np.ndarray, tolerance: float
          ) -> tuple[np.ndarray, np.ndarray]:
    """Which true positions have a detection within ``tolerance`` (M,), and which
    detections lie within ``tolerance`` of a true position (K,)."""
    from scipy.spatial import cKDTree

    found = np.asarray(found, dtype=np.float64).reshape(-1, 2)
    truth = np.asarray(truth, dtype=np.float64).reshape(-1, 2)
    if len(found) == 0 or len(truth) == 0:
        return np.zeros(len(truth), bool), np.zeros(len(found), bool)
    d_truth, _ = cKDTree(found).query(truth)
    d_found, _ = cKDTree(truth).query(found)
    return d_truth <= tolerance, d_found <= tolerance
