"""An independent generator: bead images whose PSFs come from optics code we did not write.

The project's own simulator (``core/simulation``) is one view of the world: a scalar
pupil with its Zernike phase, computed by our own matrix Fourier transforms. A method
accepted on it alone may only have learnt its quirks. Here the PSFs come from **pyotf**
(David Hoffman's implementation of Hanser et al.'s pupil model, J. Microsc. 2004, with
the sine condition and the vectorial correction of high-NA imaging, ``vec_corr="total"``):
its own pupil sampling, its own Zernike polynomials, its own propagation. The field
variation is made by varying pyotf's parameters (its Zernike phase coefficients) across
the field with the same smooth polynomials as the project's presets, so that the two
generators describe the same microscope and differ only in the optics code.

Everything else of a scene (bead layout, brightness, background, effects such as drift
or companions, the camera) is the project's, so that what is compared is the optics.
``PyotfOptics`` is an :class:`~napari_psfspace.core.simulation.optics.Optics` whose
PSFs pyotf computes; pass it where the simulator takes optics, e.g.
``random_scene(seed, optics_type=PyotfOptics)`` or ``simulate_beads(optics=...)``.

pyotf is a ``bench`` extra (``pip install -e ".[bench]"``), not a dependency of the
package: nothing in ``src`` imports it.

    python bench/independent.py   # a side-by-side look at a few PSFs of both codes
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from napari_psfspace.core.simulation import sphere_transfer
from napari_psfspace.core.simulation.optics import Optics


def _padded_span(size, drift, diameters, pixel_size) -> int:
    """Pixels across the grid a PSF of ``size`` is computed on: a half window wider on
    each side (and more for a smear or a large bead), so that the periodic wings of an
    FFT propagation stay away from the window; odd, the centre on a pixel."""
    pad = max(8, size // 4)
    if drift is not None:
        pad += int(np.ceil(np.hypot(*drift) / 2))
    if diameters is not None and len(diameters):
        pad += int(np.ceil(np.max(diameters) / pixel_size / 2))
    span = size + 2 * pad
    return span + 1 - span % 2


def _shift_and_bin(inten, total, shift, q, size, drift, diameter, pixel_size):
    """A PSF on a fine grid (``q`` samples a pixel, square, odd) shifted by ``shift``
    pixels, smeared by ``drift`` and blurred by a bead of ``diameter`` µm in Fourier
    space, summed over each pixel and cut to ``size``, as a fraction of ``total``."""
    n = inten.shape[0]
    span = n // q
    ky = sfft.fftfreq(n)[:, None]
    kx = sfft.fftfreq(n)[None, :]
    spec = sfft.fft2(sfft.ifftshift(inten))
    # cycles per fine sample
    spec *= np.exp(-2j * np.pi * (ky * shift[0] * q + kx * shift[1] * q))
    if drift is not None:
        spec *= np.sinc(ky * drift[0] * q + kx * drift[1] * q)
    if diameter is not None:
        spec *= sphere_transfer(np.hypot(ky, kx) / (pixel_size / q), diameter)
    fine = sfft.fftshift(sfft.ifft2(spec).real)
    binned = fine.reshape(span, q, span, q).sum(axis=(1, 3))
    c, h = span // 2, size // 2
    return binned[c - h:c + h + 1, c - h:c + h + 1] / total


@dataclass(frozen=True)
class PyotfOptics(Optics):
    """Optics whose PSFs pyotf computes (Hanser's pupil model, vectorial correction).

    Parameters
    ----------
    na, wavelength, pixel_size
        As :class:`~napari_psfspace.core.simulation.optics.Optics` (µm).
    immersion : float
        Refractive index of the immersion medium (above the NA).
    oversample : int
        Odd sub-sampling of each camera pixel: the intensity is computed on a grid ``q``
        times finer and summed over each pixel (pixel integration).
    vec_corr : str
        pyotf's vectorial correction ("total": both polarisations, high-NA).
    """

    immersion: float = 1.52
    oversample: int = 3
    vec_corr: str = "total"

    def psf_stack(self, noll, coefs, shifts, size, *, diameters=None, drift=None):
        """Pixel-integrated PSFs, as the simulator's ``_psf_stack`` returns them: shape
        (B, size, size), each the fraction of unit energy that falls in each pixel."""
        from pyotf.otf import HanserPSF, apply_aberration

        q = int(self.oversample)
        coefs = np.atleast_2d(np.asarray(coefs, float))
        shifts = np.asarray(shifts, float).reshape(-1, 2)
        span = _padded_span(size, drift, diameters, self.pixel_size)
        # pyotf samples the pupil at 1 / (grid extent): at least 16 samples across its
        # radius, or aberrated pupils alias
        span = max(span, int(np.ceil(16.0 / (self.cutoff * self.pixel_size))))
        span += 1 - span % 2  # odd: the centre on a pixel
        n = q * span
        na = min(self.na, 0.999 * self.immersion)
        model = HanserPSF(wl=self.wavelength * 1000.0, na=na, ni=self.immersion,
                          res=self.pixel_size * 1000.0 / q, size=n, zrange=[0.0],
                          vec_corr=self.vec_corr, condition="sine")
        jmax = max(noll) if len(noll) else 1
        out = np.empty((len(coefs), size, size))
        for b in range(len(coefs)):
            pcoefs = np.zeros(jmax)
            for j, c in zip(noll, coefs[b], strict=True):
                pcoefs[j - 1] = 2 * np.pi * c  # pyotf: radians, Noll order, rms-normalised
            m = apply_aberration(model, None, pcoefs) if len(noll) else model
            inten = np.asarray(m.PSFi, float).reshape(-1, n, n)[0]
            out[b] = _shift_and_bin(inten, inten.sum(), shifts[b], q, size, drift,
                                    None if diameters is None else float(diameters[b]),
                                    self.pixel_size)
        return np.maximum(out, 0.0)


#: psfmodels' stand-ins for the field's Zernike terms (its Gibson-Lanni model takes no
#: Zernike phase): the defocus (Noll 4) becomes the focus position, by the paraxial
#: ``z = 2 sqrt(3) c lambda / (n (1 - cos alpha))``; the primary spherical (Noll 11)
#: becomes the depth of the beads in water under an oil objective, SPHERICAL_PER_UM waves
#: rms a µm (about what the mismatch gives at NA 1.3); astigmatism, coma and trefoil have
#: no stand-in and are left out. Sample index of the mismatch:
SPHERICAL_PER_UM = 0.15
SAMPLE_INDEX = 1.33


@dataclass(frozen=True)
class PsfmodelsOptics(Optics):
    """Optics whose PSFs psfmodels computes (the vectorial Gibson-Lanni model of an oil
    objective imaging beads in water): the field's defocus and spherical aberration as a
    focus position and a depth that vary over the field; see :data:`SPHERICAL_PER_UM`.

    Parameters
    ----------
    na, wavelength, pixel_size
        As :class:`~napari_psfspace.core.simulation.optics.Optics` (µm).
    immersion : float
        Refractive index of the immersion oil (and the coverslip).
    oversample : int
        Odd sub-sampling of each camera pixel (pixel integration).
    """

    immersion: float = 1.515
    oversample: int = 3

    def psf_stack(self, noll, coefs, shifts, size, *, diameters=None, drift=None):
        """Pixel-integrated PSFs, shape (B, size, size), each the fraction of unit energy
        in each pixel (as the simulator's ``_psf_stack``)."""
        import psfmodels as pm

        q = int(self.oversample)
        coefs = np.atleast_2d(np.asarray(coefs, float))
        shifts = np.asarray(shifts, float).reshape(-1, 2)
        noll = list(noll)
        na = min(self.na, 0.999 * self.immersion)
        cos_a = np.sqrt(1 - (na / self.immersion) ** 2)
        span = _padded_span(size, drift, diameters, self.pixel_size)
        n = q * span
        params = {"NA": na, "ni": self.immersion, "ni0": self.immersion,
                  "ns": SAMPLE_INDEX}
        out = np.empty((len(coefs), size, size))
        for b in range(len(coefs)):
            c = dict(zip(noll, coefs[b], strict=True))
            depth = max(0.0, c.get(11, 0.0) / SPHERICAL_PER_UM)
            z = (2 * np.sqrt(3) * c.get(4, 0.0) * self.wavelength
                 / (self.immersion * (1 - cos_a)))
            inten = np.asarray(pm.vectorial_psf([depth + z], nx=n, dxy=self.pixel_size / q,
                                                pz=depth, wvl=self.wavelength, params=params,
                                                normalize=False), float)[0]
            # unit energy: the in-focus PSF's total on a grid twice as wide
            total = float(np.asarray(pm.vectorial_psf(
                [depth], nx=2 * n + 1, dxy=self.pixel_size / q, pz=depth,
                wvl=self.wavelength, params=params, normalize=False), float)[0].sum())
            out[b] = _shift_and_bin(inten, total, shifts[b], q, size, drift,
                                    None if diameters is None else float(diameters[b]),
                                    self.pixel_size)
        return np.maximum(out, 0.0)


def _demo() -> None:
    from napari_psfspace.core.simulation import FieldAberrations, simulate_psf

    field = FieldAberrations.preset("moderate")
    for na in (0.8, 1.2, 1.45):
        ours = Optics(na=na, wavelength=0.6, pixel_size=0.08)
        theirs = PyotfOptics(na=na, wavelength=0.6, pixel_size=0.08)
        for y, x in ((0.0, 0.0), (255.0, 255.0)):
            z = field.coefficients(y, x, (512, 512))
            a = simulate_psf(z, optics=ours, size=31)
            b = simulate_psf(z, optics=theirs, size=31)
            diff = np.linalg.norm(a / a.sum() - b / b.sum()) / np.linalg.norm(b / b.sum())
            print(f"NA {na}: at ({y:.0f}, {x:.0f}) peak ours {a.max():.4f} pyotf "
                  f"{b.max():.4f}, relative difference {diff:.3f}")


if __name__ == "__main__":
    _demo()
