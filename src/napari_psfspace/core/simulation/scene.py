"""The bead scene: :func:`simulate_beads` places beads, renders their space-varying
PSFs (:mod:`.optics`, :mod:`.aberrations`), adds the background, the effects asked for
(:mod:`.effects`) and the camera (:mod:`.camera`), and returns the image with its
:class:`~.truth.SimulationTruth`.

Model: eq. (6) of Debarnot, Escande, Mangeat & Weiss, "Learning low-dimensional models
of microscopes", section 3.1.1 (see :mod:`.optics`). Each bead is rendered with the exact
PSF at its own position (Zernike coefficients evaluated there) and sub-pixel offset, on a
window of radius ``RENDER_RADIUS_FACTOR * psf_radius`` (clipped at the image border).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..common.validate import check_camera, check_exposure, check_int, check_memory, check_shape
from .aberrations import FieldAberrations, as_aberrations
from .camera import as_range, camera, camera_adu, digitise
from .effects import (
    EFFECTS,
    background_structure,
    bead_diameters,
    check_effects,
    companions,
    fixed_pattern,
    hot_pixels,
    illumination_map,
    nonlinear,
    typical_peak,
)
from .optics import PSF_ENERGY_FRACTION, RENDER_RADIUS_FACTOR, Optics, field_psf_radius
from .render import place_beads, render_beads, smooth_background, spawn
from .truth import SimulationTruth

__all__ = ["simulate_beads"]


def simulate_beads(
    shape: tuple[int, int] = (1024, 1024),
    n_beads: int = 150,
    *,
    aberrations: str | FieldAberrations | None = "moderate",
    optics: Optics | None = None,
    amplitude: float | tuple[float, float] = (2e4, 6e4),
    background: float | tuple[float, float] = (50.0, 150.0),
    gain: float = 2.0,
    offset: float = 100.0,
    read_noise: float = 1.5,
    min_separation: float | None = None,
    border: float | None = None,
    dtype: np.dtype | type = np.uint16,
    seed: int | np.random.Generator | None = 0,
    psf_energy: float = PSF_ENERGY_FRACTION,
    effects: Mapping[str, Any] | None = None,
    bead_photons: np.ndarray | None = None,
) -> tuple[np.ndarray, SimulationTruth]:
    """Simulate a camera image of fluorescent beads seen through a space-varying PSF.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` image shape, pixels.
    n_beads : int
        Number of beads.
    aberrations : str, FieldAberrations or None
        Preset name (``"none"``, ``"moderate"``, ``"strong"``), explicit
        aberration field, or ``None`` (aberration-free).
    optics : Optics or None
        Default ``Optics()``.
    amplitude : float or (float, float)
        Total photons per bead, uniform in ``[low, high]``.
    background : float or (float, float)
        Smooth background, photons/pixel, rescaled to span ``[low, high]``.
    gain : float
        ADU per photo-electron.
    offset : float
        Camera offset, ADU.
    read_noise : float
        Read noise, electrons rms (``read_noise * gain`` ADU rms).
    min_separation : float or None
        Minimum distance between bead centres, pixels; default
        ``2.5 * psf_radius``.
    border : float or None
        Minimum distance of bead centres from the border pixel centres,
        pixels; default ``psf_radius``.
    dtype : numpy dtype
        Output dtype. Integer dtypes are rounded and clipped to their range;
        float dtypes are neither.
    seed : int, Generator or None
        Seed of the one generator of everything (positions, amplitudes, background, noise).
    psf_energy : float
        Energy fraction defining ``truth.psf_radius``.
    bead_photons : array_like of shape (n_beads,), optional
        Total photons of each bead instead of ``amplitude``'s (e.g. a log-normal spread).
    effects : Mapping[str, Any] or None
        Effects beyond the PSF model to inject, each key switching one on (the keys and
        their values: :mod:`.effects`); all recorded in ``truth.effects``. Each effect
        draws from its own child of the seeded generator: ``effects=None`` (or ``{}``)
        is bit-identical to not passing it. Invalid keys or values raise ValueError.

    Returns
    -------
    image : ndarray, shape (H, W), ``dtype``
        Camera image in ADU.
    truth : SimulationTruth
        Positions, amplitudes, background, optics, aberrations, camera
        parameters, recommended PSF radius, per-bead peak SNR and effects.
        With effects, ``amplitudes`` are the photons collected from each
        primary bead (bead-size and illumination factors included) and
        ``background`` is the expected background photons in the image
        (illuminated smooth background plus background structure).

    Raises
    ------
    ValueError
        If the beads cannot be placed with the requested separation/border,
        or for an unknown effect or an invalid effect value.
    """
    (shape, n_beads, optics, aberrations, amp_range, bg_range, (gain, offset, read_noise, dtype),
     effect_params) = _checked(shape, n_beads, aberrations, optics, amplitude, background, gain,
                               offset, read_noise, dtype, seed, psf_energy, effects)
    rng = np.random.default_rng(seed)
    psf_radius = field_psf_radius(aberrations, optics, shape, psf_energy)
    border = float(psf_radius if border is None else border)
    min_separation = float(2.5 * psf_radius if min_separation is None else min_separation)
    positions = place_beads(rng, shape, n_beads, min_separation, border)
    amp_range, amplitudes = _amplitudes(n_beads, bead_photons, amp_range, rng)
    bg = smooth_background(rng, shape, *bg_range)
    if effect_params:
        return _simulate_with_effects(rng, effect_params, shape, positions, amplitudes, bg,
                                      aberrations, optics, amp_range, gain, offset,
                                      read_noise, dtype, psf_radius)
    return _plain(shape, aberrations, optics, gain, offset, read_noise, dtype, rng, psf_radius,
                  positions, amplitudes, bg)


def _checked(shape, n_beads, aberrations, optics, amplitude, background, gain, offset, read_noise,
             dtype, seed, psf_energy, effects):
    """The arguments checked (one clear line for a bad value before any work), the defaults
    filled in."""
    shape = check_shape(shape)
    # the photon image, its noise and the camera's: about six float64 images
    check_memory(6 * 8.0 * shape[0] * shape[1], f"`shape` {shape}: a {shape[0]} x {shape[1]} "
                 "image")
    n_beads = check_int(n_beads, "n_beads", minimum=0)
    if seed is not None and not isinstance(seed, np.random.Generator):
        check_int(seed, "seed", minimum=0)
    optics = Optics() if optics is None else optics
    aberrations = as_aberrations(aberrations)
    amp_range = as_range(amplitude, "amplitude")
    bg_range = as_range(background, "background")
    gain, offset, read_noise, dtype = check_camera(gain, offset, read_noise, dtype)
    check_exposure(gain, offset, bg_range[1], dtype)
    effect_params = check_effects(effects, shape, dtype, offset)
    if not 0.0 < psf_energy < 1.0:
        raise ValueError(f"psf_energy must be in (0, 1), got {psf_energy!r}")
    return (shape, n_beads, optics, aberrations, amp_range, bg_range,
            (gain, offset, read_noise, dtype), effect_params)


def _amplitudes(n_beads, bead_photons, amp_range, rng):
    """Each bead's photons (drawn uniformly from ``amp_range``, or given) and their range."""
    if bead_photons is None:
        amplitudes = rng.uniform(*amp_range, size=n_beads)
    else:
        amplitudes = np.asarray(bead_photons, dtype=np.float64).reshape(-1)
        if len(amplitudes) != n_beads or np.any(~np.isfinite(amplitudes)) or np.any(
                amplitudes < 0):
            raise ValueError(f"bead_photons must hold n_beads={n_beads} finite non-negative "
                             f"numbers, got shape {np.shape(bead_photons)}")
        if n_beads:
            amp_range = (float(amplitudes.min()), float(amplitudes.max()))
    return amp_range, amplitudes


def _plain(shape, aberrations, optics, gain, offset, read_noise, dtype, rng, psf_radius, positions,
           amplitudes, bg):
    """The scene without effects: the beads rendered on the background, the camera, the truth."""
    photons = bg.astype(np.float64)
    peaks = render_beads(
        photons, positions, amplitudes, aberrations, optics, RENDER_RADIUS_FACTOR * psf_radius
    )
    image = camera(rng, photons, gain, offset, read_noise, dtype)

    peak = amplitudes * peaks
    centres = np.clip(np.rint(positions).astype(int), 0, np.array(shape) - 1)
    local_bg = bg[centres[:, 0], centres[:, 1]].astype(np.float64)
    truth = SimulationTruth(
        shape=shape,
        positions=positions,
        amplitudes=amplitudes,
        background=bg,
        optics=optics,
        aberrations=aberrations,
        gain=float(gain),
        offset=float(offset),
        read_noise=float(read_noise),
        psf_radius=psf_radius,
        peak_snr=peak / np.sqrt(peak + local_bg + read_noise**2),
    )
    return image, truth


def _simulate_with_effects(
    rng: np.random.Generator,
    params: dict[str, Any],
    shape: tuple[int, int],
    positions: np.ndarray,
    amplitudes: np.ndarray,
    bg: np.ndarray,
    aberrations: FieldAberrations,
    optics: Optics,
    amp_range: tuple[float, float],
    gain: float,
    offset: float,
    read_noise: float,
    dtype: np.dtype,
    psf_radius: int,
) -> tuple[np.ndarray, SimulationTruth]:
    """The rest of :func:`simulate_beads` with the validated ``params`` effects injected.

    Order: bead sizes (amplitude factors), companions, illumination (beads
    and smooth background), background structure, rendering (bead size,
    drift), nonlinearity, camera noise (main generator, as without effects),
    row/column offsets, hot pixels, saturation and digitisation.
    """
    rngs = dict(zip(EFFECTS, spawn(rng, len(EFFECTS)), strict=True))
    fx: dict[str, Any] = {}
    n = len(positions)
    all_pos, all_amp, all_diam, background, drift = _scene_effects(
            params, shape, positions, amplitudes.astype(np.float64), bg, psf_radius, rngs, fx)
    photons = background.copy()
    peaks = render_beads(
        photons,
        all_pos,
        all_amp,
        aberrations,
        optics,
        RENDER_RADIUS_FACTOR * psf_radius,
        all_diam,
        drift,
    )[:n]
    amplitudes = all_amp[:n]

    if "nonlinearity" in params:
        e_ref = float(photons.max())
        photons = nonlinear(photons, params["nonlinearity"], e_ref)
        fx.update(nonlinearity=params["nonlinearity"], nonlinearity_reference=e_ref)
    adu = camera_adu(rng, photons, gain, offset, read_noise)
    image = _camera_effects(adu, params, rngs, fx, shape, amplitudes, peaks, aberrations,
                            optics, amp_range, gain, dtype)

    peak = amplitudes * peaks
    centres = np.clip(np.rint(positions).astype(int), 0, np.array(shape) - 1)
    local_bg = background[centres[:, 0], centres[:, 1]]
    truth = SimulationTruth(
        shape=shape,
        positions=positions,
        amplitudes=amplitudes,
        background=background.astype(np.float32),
        optics=optics,
        aberrations=aberrations,
        gain=float(gain),
        offset=float(offset),
        read_noise=float(read_noise),
        psf_radius=psf_radius,
        peak_snr=peak / np.sqrt(peak + local_bg + read_noise**2),
        effects=fx,
    )
    return image, truth


def _scene_effects(params, shape, positions, amplitudes, bg, psf_radius, rngs, fx):
    """The scene's effects before rendering: bead sizes (amplitude factors), companions,
    illumination (beads and smooth background), background structure, drift; each recorded
    in ``fx``."""
    n = len(positions)
    diameters = None
    if "bead_size" in params:
        diameters, factors = bead_diameters(rngs["bead_size"], n, params["bead_size"])
        amplitudes = amplitudes * factors
        fx.update(bead_size=params["bead_size"], bead_diameters=diameters)

    all_pos, all_amp, all_diam = positions, amplitudes, diameters
    if "neighbours" in params:
        owners, comp_pos, comp_factor = companions(
            rngs["neighbours"], positions, params["neighbours"], psf_radius
        )
        all_pos = np.concatenate([positions, comp_pos])
        all_amp = np.concatenate([amplitudes, comp_factor * amplitudes[owners]])
        if diameters is not None:
            all_diam = np.concatenate([diameters, diameters[owners]])

    background = bg.astype(np.float64)
    if "illumination" in params:
        strength, centre = params["illumination"]
        centre, illumination = illumination_map(rngs["illumination"], shape, strength, centre)
        field_map = illumination(np.arange(shape[0])[:, None], np.arange(shape[1])[None, :])
        factors = illumination(all_pos[:, 0], all_pos[:, 1])
        all_amp = all_amp * factors
        background *= field_map
        fx.update(
            illumination=strength,
            illumination_centre=centre,
            illumination_map=field_map.astype(np.float32),
            illumination_factors=factors[:n],
        )
    if "background_structure" in params:
        structure = background_structure(
            rngs["background_structure"], shape, params["background_structure"], psf_radius
        )
        background += structure
        fx.update(
            background_structure=params["background_structure"],
            background_structure_map=structure,
        )
    if "neighbours" in params:
        fx.update(
            neighbours=params["neighbours"],
            companion_positions=all_pos[n:],
            companion_amplitudes=all_amp[n:],
            companion_of=owners,
        )
        if diameters is not None:
            fx["companion_diameters"] = all_diam[n:]
    drift = params.get("drift")
    if drift is not None:
        fx["drift"] = drift
    return all_pos, all_amp, all_diam, background, drift


def _camera_effects(adu, params, rngs, fx, shape, amplitudes, peaks, aberrations, optics,
                    amp_range, gain, dtype):
    """The camera's effects on the ADU image after the noise: row and column offsets, hot
    pixels, saturation; then digitised."""
    if "row_offsets" in params:
        rows = fixed_pattern(rngs["row_offsets"], shape[0], params["row_offsets"])
        adu += rows[:, None]
        fx.update(row_offsets=params["row_offsets"], row_offset_values=rows)
    if "column_offsets" in params:
        cols = fixed_pattern(rngs["column_offsets"], shape[1], params["column_offsets"])
        adu += cols[None, :]
        fx.update(column_offsets=params["column_offsets"], column_offset_values=cols)
    if "hot_pixels" in params:
        hot = params["hot_pixels"]
        if isinstance(hot, tuple):  # factors of the brightest expected bead peak
            count, factors = hot
            top = float(np.max(amplitudes * peaks)) if len(amplitudes) else 0.0
            where, values = hot_pixels(rngs["hot_pixels"], shape, count, gain * top, factors)
        else:
            count = hot
            typical = gain * typical_peak(amplitudes, peaks, amp_range, aberrations, optics,
                                           shape)
            where, values = hot_pixels(rngs["hot_pixels"], shape, count, typical)
        adu[where[:, 0], where[:, 1]] += values
        fx.update(hot_pixels=count, hot_pixel_positions=where, hot_pixel_values=values)
    level = params.get("saturation")
    if level is not None:
        rounded = np.rint(adu) if np.issubdtype(dtype, np.integer) else adu
        fx.update(saturation=level, saturated_pixels=int(np.count_nonzero(rounded >= level)))
    image = digitise(adu, dtype, level)
    return image
