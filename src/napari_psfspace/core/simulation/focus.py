"""Through-focus bead stacks: the same slide seen at many focus positions.

A bead z-stack is the field of beads on a coverslip imaged at a series of focus
positions ``z``: in focus a small spot, out of focus a disk with rings (widefield) whose
size grows with ``|z|``. The defocus of a distance ``z`` (µm) is the exact pupil phase of
a displacement in a medium of index ``n``, not its paraxial (quadratic) part:

.. math:: W(\\rho) = \\frac{z}{\\lambda} \\sqrt{n^2 - \\mathrm{NA}^2 \\rho^2}
          \\quad \\text{(waves)},

expanded on the rotationally symmetric Zernike polynomials up to radial order
:data:`MAX_ORDER` (:func:`defocus_zernike`, which returns the rms of what is left), which
the simulator's pupil takes as it is. At high NA the quadratic (paraxial) term alone is
not the defocus: the higher orders carry a spherical-like part that grows with the NA.

:func:`simulate_focus_series` renders such a stack, with the microscope's own
field-dependent aberrations on top, every slice its own noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..common.validate import check_camera, check_exposure, check_memory, check_shape
from .aberrations import FieldAberrations, as_aberrations
from .camera import as_range, camera
from .optics import RENDER_RADIUS_FACTOR, Optics, field_psf_radius, psf_stack
from .render import place_beads, render_beads, smooth_background, spawn

#: Highest radial order of the Zernike expansion of the defocus phase.
MAX_ORDER = 12
#: Noll index of the rotationally symmetric polynomial of radial order n (n even).
_SYMMETRIC_NOLL = {2: 4, 4: 11, 6: 22, 8: 37, 10: 56, 12: 79}


def immersion_index(na: float) -> float:
    """A plausible immersion index for an objective of this NA: air up to 0.95, water
    up to 1.27, glycerol up to 1.4, oil beyond."""
    if na <= 0.95:
        return 1.0
    if na <= 1.27:
        return 1.333
    if na <= 1.4:
        return 1.46
    return 1.518


def _radial(n: int, rho: np.ndarray) -> np.ndarray:
    """The rms-normalised radial Zernike polynomial ``sqrt(n + 1) R_n^0(rho)``."""
    from math import factorial

    out = np.zeros_like(rho)
    for k in range(n // 2 + 1):
        c = ((-1) ** k * factorial(n - k)
             / (factorial(k) * factorial(n // 2 - k) * factorial(n // 2 - k)))
        out += c * rho ** (n - 2 * k)
    return np.sqrt(n + 1.0) * out


def defocus_zernike(z_um: float, optics: Optics, *, index: float | None = None
                    ) -> tuple[dict[int, float], float]:
    """Zernike coefficients (waves rms) of a focus displacement of ``z_um`` micrometres.

    Parameters
    ----------
    z_um : float
        Displacement of the focus from the bead plane, µm (either sign).
    optics : Optics
    index : float, optional
        Refractive index of the immersion medium; default :func:`immersion_index`.

    Returns
    -------
    coefficients : dict
        Noll index -> waves rms, the symmetric polynomials up to :data:`MAX_ORDER`.
    residual : float
        Rms (waves) of the part of the phase beyond them.
    """
    n_med = immersion_index(optics.na) if index is None else float(index)
    if optics.na >= n_med:
        raise ValueError(f"`index` = {n_med:g} must exceed the NA {optics.na:g}.")
    rho = (np.arange(4000) + 0.5) / 4000
    phase = float(z_um) / optics.wavelength * np.sqrt(n_med**2 - (optics.na * rho) ** 2)
    weight = 2 * rho / len(rho)  # (1 / pi) * integral over the disk, per unit rho
    phase -= np.sum(phase * weight)  # piston
    coefs, left = {}, phase.copy()
    for order, noll in _SYMMETRIC_NOLL.items():
        if order > MAX_ORDER:
            break
        r = _radial(order, rho)
        c = float(np.sum(phase * r * weight))
        coefs[noll] = c
        left -= c * r
    return coefs, float(np.sqrt(np.sum(left**2 * weight)))


#: The most focus positions a simulated series takes (each slice's PSF field is computed).
MAX_SLICES = 1000


@dataclass
class FocusSeries:
    """What :func:`simulate_focus_series` rendered.

    Attributes
    ----------
    z_um : ndarray of shape (Z,)
        Focus position of each slice relative to the bead plane, µm.
    positions : ndarray of shape (M, 2)
        Bead centres (row, column), pixels, the same in every slice.
    amplitudes : ndarray of shape (M,)
        Photons of each bead per slice.
    psf_radius : ndarray of shape (Z,), int
        Each slice's PSF radius (90 % of the energy, the widest over the field), pixels.
    optics : Optics
    aberrations : FieldAberrations
        The microscope's own field, before the defocus of each slice.
    shape : (int, int)
        ``(H, W)`` of a slice.
    bead_z_um : ndarray of shape (M,), optional
        Each bead's height above the bead plane, µm: its focus lies on the slice at
        ``z_um == bead_z_um`` (None: every bead on the plane).
    """

    z_um: np.ndarray
    positions: np.ndarray
    amplitudes: np.ndarray
    psf_radius: np.ndarray
    optics: Optics
    aberrations: FieldAberrations
    shape: tuple[int, int] = (0, 0)
    bead_z_um: np.ndarray | None = None

    def psf_at(self, y: float, x: float, size: int) -> np.ndarray:
        """The true 3D PSF of a point on the bead plane at ``(y, x)``: its image on every
        slice, shape (Z, size, size), centred on pixel ``size // 2`` (no sub-pixel shift).
        A slice's PSF integrates to 1 over the whole plane (the window holds less of a
        wide one)."""
        out = np.empty((len(self.z_um), int(size), int(size)))
        for k in range(len(self.z_um)):
            field = self.slice_aberrations(k)
            coefs = field.coefficient_matrix(np.array([float(y)]), np.array([float(x)]),
                                             self.shape)
            out[k] = psf_stack(field.noll_indices, coefs, np.zeros((1, 2)), self.optics,
                               int(size))[0]
        return out

    @property
    def focus_index(self) -> int:
        """The slice nearest the bead plane."""
        return int(np.argmin(np.abs(self.z_um)))

    def slice_aberrations(self, k: int) -> FieldAberrations:
        """The field of slice ``k``: the microscope's own plus the slice's defocus."""
        return with_defocus(self.aberrations, float(self.z_um[k]), self.optics)


def with_defocus(base: FieldAberrations, z_um: float, optics: Optics) -> FieldAberrations:
    """``base`` with the defocus of ``z_um`` added over the whole field."""
    terms = {j: list(c) for j, c in base.terms.items()}
    for j, c in defocus_zernike(z_um, optics)[0].items():
        terms.setdefault(j, [0.0] * 6)[0] += c
    return FieldAberrations({j: tuple(c) for j, c in terms.items()})


def simulate_focus_series(
    shape: tuple[int, int] = (384, 384),
    n_beads: int = 12,
    z_um=(-2.0, -1.0, 0.0, 1.0, 2.0),
    *,
    optics: Optics | None = None,
    aberrations: str | FieldAberrations | None = "moderate",
    amplitude: float | tuple[float, float] = (5e4, 1.5e5),
    background: float | tuple[float, float] = (20.0, 40.0),
    gain: float = 1.0,
    offset: float = 100.0,
    read_noise: float = 1.5,
    min_separation: float | None = None,
    dtype=np.uint16,
    seed: int = 0,
    bead_z=None,
) -> tuple[np.ndarray, FocusSeries]:
    """A bead z-stack: beads on one plane (or at heights ``bead_z``), seen at the focus
    positions ``z_um``.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of every slice, pixels.
    n_beads : int
    z_um : sequence of float
        Focus of each slice relative to the bead plane, µm.
    optics : Optics, optional
        Default ``Optics()``.
    aberrations : str or FieldAberrations
        The microscope's own field (a preset name or a field), the same in every slice.
    amplitude : float or (float, float)
        Photons of each bead per slice, uniform in the range.
    background : float or (float, float)
        Smooth background, photons per pixel, the same in every slice.
    gain, offset, read_noise : float
        Camera: ADU per electron, ADU, electrons rms.
    min_separation : float, optional
        Least distance between beads, pixels; default 2.5 widest PSF radii (isolated).
    dtype : dtype
    seed : int
        Seeds the layout (the same in every slice) and each slice's noise.
    bead_z : callable, optional
        ``bead_z(positions, rng)`` -> each bead's height above the bead plane, µm, shape
        (M,) (a tilted or curved slide, beads at scattered depths): a bead at height
        ``o`` is in focus on the slice at ``z_um == o``.

    Returns
    -------
    stack : ndarray of shape (Z, H, W)
    series : FocusSeries
    """
    optics = Optics() if optics is None else optics
    base = as_aberrations(aberrations)
    try:
        z = np.asarray(z_um, float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"`z_um` must be focus positions in µm, got {z_um!r}") from None
    shape = check_shape(shape)
    gain, offset, read_noise, dtype = check_camera(gain, offset, read_noise, dtype)
    check_exposure(gain, offset, as_range(background, "background")[1], dtype)
    if not 1 <= len(z) <= MAX_SLICES or not np.isfinite(z).all():
        raise ValueError(f"`z_um` must hold 1 to {MAX_SLICES} finite focus positions, got "
                         f"{len(z)}" + ("" if np.isfinite(z).all() else " with NaN"))
    check_memory(np.dtype(dtype).itemsize * len(z) * shape[0] * shape[1]
                 + 6 * 8.0 * shape[0] * shape[1],
                 f"`z_um`, `shape`: a stack of {len(z)} slices of {shape[0]} x {shape[1]}")
    radii = np.array([field_psf_radius(with_defocus(base, float(zk), optics), optics, shape)
                      for zk in z], int)
    rng = np.random.default_rng(seed)
    sep = 2.5 * float(radii.max()) if min_separation is None else float(min_separation)
    positions = place_beads(rng, shape, int(n_beads), sep, float(radii.min()))
    heights = None
    if bead_z is not None:
        heights = np.asarray(bead_z(positions, rng), float).reshape(-1)
        if heights.shape != (len(positions),) or not np.isfinite(heights).all():
            raise ValueError(f"`bead_z` must give {len(positions)} finite heights (µm), got "
                             f"shape {heights.shape}")
        # the widest PSF a slice holds: the farthest bead's defocus
        radii = np.array([max(field_psf_radius(with_defocus(base, float(zk - o), optics),
                                               optics, shape)
                              for o in (heights.min(), heights.max()))
                          for zk in z], int)
    amplitudes = rng.uniform(*as_range(amplitude, "amplitude"), size=len(positions))
    bg = smooth_background(rng, shape, *as_range(background, "background"))
    noise = spawn(rng, len(z))
    stack = np.empty((len(z), *shape), dtype=np.dtype(dtype))
    for k, zk in enumerate(z):
        photons = bg.astype(np.float64)
        reach = int(RENDER_RADIUS_FACTOR * radii[k])
        if heights is None:
            render_beads(photons, positions, amplitudes, with_defocus(base, float(zk), optics),
                         optics, reach)
        else:  # each bead at its own height: its own defocus on this slice
            for m in range(len(positions)):
                render_beads(photons, positions[m:m + 1], amplitudes[m:m + 1],
                             with_defocus(base, float(zk - heights[m]), optics), optics,
                             reach)
        stack[k] = camera(noise[k], photons, gain, offset, read_noise, np.dtype(dtype))
    return stack, FocusSeries(z, positions, amplitudes, radii, optics, base, shape, heights)


__all__ = ["FocusSeries", "defocus_zernike", "immersion_index", "simulate_focus_series",
           "with_defocus"]
