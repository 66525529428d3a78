"""Which 2-D PSFs are spots: the share of the light in the central lobe, in focus and out.

    python bench/run.py spot_shape

A Gaussian FWHM is quoted for a 2-D PSF only while it is a spot
(``measures.spot_measures``: its central lobe holds at least ``SPOT_CORE`` of its
light). This bench measures that share on widefield PSFs of three optics codes: this
project's scalar model (Zernike defocus and aberrations), pyotf's vectorial
``HanserPSF`` and psfmodels' ``vectorial_psf`` (the ``bench`` extra), at NA 0.9 and 1.4,
in focus and defocused by 0.25 to 1.5 µm, each binned to 65 nm pixels from fifths of a
pixel, with and without Poisson noise. A table a PSF; the last line: the smallest share
of the spots (within a quarter of the axial FWHM of focus, the aberrations included),
the largest of the rings (:data:`RING_DEPTHS` axial FWHMs from focus or more), and
``SPOT_CORE`` between them.
"""

from __future__ import annotations

import numpy as np

from bench_fwhm_reference import simulated_psf
from benchlib import table
from napari_psfspace.core.common.measures import SPOT_CORE, diffraction_limit, spot_measures
from napari_psfspace.core.simulation.optics import Optics, simulate_psf

PIXEL = 0.065
WAVELENGTH = 0.6
DEFOCUS = (0.0, 0.25, 0.5, 1.0, 1.5)
ABERRATIONS = ({5: 0.15}, {7: 0.15}, {7: 0.3}, {11: 0.1})
SIZE = 49
#: A PSF this many axial FWHMs (the diffraction limit's) from focus or more is a ring.
RING_DEPTHS = 1.5


def immersion(na: float) -> float:
    return 1.515 if na > 1.0 else 1.33


def ours(na: float, dz: float, zernike: dict | None = None) -> np.ndarray:
    """This project's scalar widefield PSF, defocus ``dz`` µm as Zernike defocus (Noll 4,
    waves rms: the path difference at the pupil's edge, n (1 - cos a) dz, over
    2 sqrt 3)."""
    n = immersion(na)
    cos_a = np.sqrt(1.0 - (na / n) ** 2)
    z4 = n * (1.0 - cos_a) * dz / WAVELENGTH / (2 * np.sqrt(3))
    coefs = {4: z4, **(zernike or {})}
    return simulate_psf(coefs, optics=Optics(na=na, wavelength=WAVELENGTH,
                                             pixel_size=PIXEL), size=SIZE)


def external(generator: str, na: float, dz: float) -> np.ndarray:
    """The plane ``dz`` µm from focus of an external code's PSF, binned to pixels."""
    q, nz = 5, 3
    fine, (kz, _, _), _ = simulated_psf(generator, na, WAVELENGTH, PIXEL, max(dz, 0.05),
                                        nz, q=q, size=SIZE)
    plane = fine[-1] if dz > 0 else fine[kz]
    n = (plane.shape[0] // q) * q
    return plane[:n, :n].reshape(n // q, q, n // q, q).sum(axis=(1, 3))


def main() -> None:
    rng = np.random.default_rng(0)
    rows = []
    for na in (0.9, 1.4):
        depth = diffraction_limit(na, WAVELENGTH)["axial"]
        cases = [("ours", dz, None) for dz in DEFOCUS]
        cases += [("ours", 0.0, z) for z in ABERRATIONS]
        cases += [(g, dz, None) for g in ("pyotf", "psfmodels") for dz in DEFOCUS]
        for gen, dz, zern in cases:
            psf = ours(na, dz, zern) if gen == "ours" else external(gen, na, dz)
            psf = psf / psf.sum()
            noisy = rng.poisson(psf * 2e4 + 20.0).astype(float)
            clean, loud = spot_measures(psf), spot_measures(noisy)
            kind = ("spot" if dz <= depth / 4 else "ring" if dz >= RING_DEPTHS * depth
                    else "between")
            rows.append({"code": gen, "na": na, "defocus_um": dz,
                         "aberration": "" if not zern else ", ".join(
                             f"Z{k} {v}" for k, v in zern.items()),
                         "truth": kind, "share": clean["core_share"],
                         "share_noisy": loud["core_share"],
                         "fwhm_px": clean["fwhm_lateral"],
                         "ring_px": clean["ring_radius"]})
    print(table(rows, [("code", "s"), ("na", ".1f"), ("defocus_um", ".2f"),
                       ("aberration", "s"), ("truth", "s"), ("share", ".3f"),
                       ("share_noisy", ".3f"), ("fwhm_px", ".2f"), ("ring_px", ".0f")]))
    spots = [min(r["share"], r["share_noisy"]) for r in rows if r["truth"] == "spot"]
    rings = [np.nanmax([r["share"], r["share_noisy"]]) for r in rows
             if r["truth"] == "ring" and np.isfinite([r["share"], r["share_noisy"]]).any()]
    unmeasured = sum(1 for r in rows if r["truth"] == "ring"
                     and not np.isfinite([r["share"], r["share_noisy"]]).any())
    print(f"spots (within a quarter of the axial FWHM of focus): smallest share "
          f"{min(spots):.3f}; rings ({RING_DEPTHS} axial FWHMs from focus or more): largest "
          f"share {max(rings):.3f} ({unmeasured} with no share: light beyond the window, "
          f"no FWHM either); SPOT_CORE {SPOT_CORE}")


if __name__ == "__main__":
    main()
