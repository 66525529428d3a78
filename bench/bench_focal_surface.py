"""The focal surface of a 3D estimate against a planted one, and what registering the
beads to it does to the axial width.

    python bench/run.py focal_surface [--seeds 10 11 12]

Each scene: a bead z-stack simulated by the project's focus series (NA 1.4, 600 nm,
100 nm pixels and planes, +-1.2 µm, 512 x 512, 36 beads, no aberration but defocus) on
a slide that is tilted (0.6 µm rise across the diagonal), curved (0.4 µm sag centre to
corner) or both, with the beads on the slide (``scatter`` 0) or scattered uniformly
+-0.5 µm about it. Columns:

* ``rms_nm``: the fitted surface less the planted one, rms over a 9 x 9 grid of the
  field, nm; ``bound_nm``: what least squares allows, ``sd sqrt(p / n)`` (``sd`` the
  beads' scatter, ``scatter / sqrt(3)``, ``p`` the surface's terms, ``n`` its beads),
  or the 100 nm the issue asks where that is smaller;
* ``axial_x``: the model's axial FWHM at the field's centre over the true PSF's there
  (the same measure on both); ``unreg_x``: the same for the mean of the beads' patches
  cut on one plane without registration (what the estimate did before).
"""

from __future__ import annotations

import argparse

import numpy as np

from benchlib import table
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.simulation.focus import simulate_focus_series
from napari_psfspace.core.simulation.optics import Optics
from napari_psfspace.core.volume import iter_estimate_operator_3d
from napari_psfspace.core.volume.focal_surface import design
from napari_psfspace.core.volume.measures import model_measures, psf_measures
from napari_psfspace.core.volume.patches3d import extract_patches_3d

SHAPE = (512, 512)
DZ = 0.1
TERMS = ("constant", "tilt_row", "tilt_col", "curvature")
#: The slides: coefficients of TERMS, µm (u, v: field coordinates over half the diagonal;
#: a tilt coefficient t rises 2 t across it, the curvature is the sag to a corner).
SLIDES = {"tilted": (0.0, 0.24, -0.18, 0.0), "curved": (-0.2, 0.0, 0.0, 0.4),
          "both": (-0.2, 0.24, -0.18, 0.4)}


def scene(slide: str, scatter: float, seed: int) -> dict:
    coef = np.array(SLIDES[slide])

    def heights(pos, rng):
        return design(pos, SHAPE, TERMS) @ coef + rng.uniform(-scatter, scatter, len(pos))

    z = np.round(np.arange(-1.2, 1.2 + DZ / 2, DZ), 6)
    stack, series = simulate_focus_series(SHAPE, 36, z, optics=Optics(1.4, 0.6, 0.1),
                                          aberrations=None, seed=seed, bead_z=heights,
                                          min_separation=45)
    est = run_with_progress(iter_estimate_operator_3d(stack, psf_radius=10,
                                                      voxel_size=(DZ, 0.1, 0.1)))
    s = est.surface
    plane0 = float(np.interp(0.0, series.z_um, np.arange(len(series.z_um))))
    grid = np.stack(np.meshgrid(np.linspace(0, SHAPE[0] - 1, 9),
                                np.linspace(0, SHAPE[1] - 1, 9), indexing="ij"),
                    -1).reshape(-1, 2)
    err = (s(grid) - plane0) * DZ - design(grid, SHAPE, TERMS) @ coef
    c = (np.array(SHAPE) - 1) / 2
    true = psf_measures(series.psf_at(*c, est.operator.kernel_shape[1]))["fwhm_axial"]
    model = model_measures(est.operator, c[None])["fwhm_axial"][0]
    raw = extract_patches_3d(stack.astype(np.float32), est.patches.centers, est.patches.r,
                             plane=series.focus_index, z_radius=est.operator.plane)
    unreg = psf_measures(raw.psf[raw.flux > 0].mean(axis=0))["fwhm_axial"]
    n = int(s.n_used)
    bound = max(scatter / np.sqrt(3) * np.sqrt(len(s.terms) / n) * 1000, 100.0)
    return {"slide": slide, "scatter_um": scatter, "seed": seed, "n": n,
            "off": int(s.off.sum()), "rms_nm": float(np.sqrt(np.mean(err ** 2)) * 1000),
            "bound_nm": bound, "axial_x": model / true, "unreg_x": unreg / true}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[10, 11, 12])
    args = ap.parse_args()
    rows = []
    for slide in SLIDES:
        for scatter in (0.0, 0.5):
            for seed in args.seeds:
                rows.append(scene(slide, scatter, seed))
                r = rows[-1]
                print(f"{slide} +-{scatter} s{seed}: {r['rms_nm']:.0f} nm rms (bound "
                      f"{r['bound_nm']:.0f}), axial x{r['axial_x']:.3f}, unregistered "
                      f"x{r['unreg_x']:.3f}", flush=True)
    print("\nThe focal surface against the planted slide, and the axial FWHM at the centre "
          "over the truth's (registered / not)")
    print(table(rows, [("slide", "s"), ("scatter_um", ".1f"), ("seed", "d"), ("n", "d"),
                       ("off", "d"), ("rms_nm", ".0f"), ("bound_nm", ".0f"),
                       ("axial_x", ".3f"), ("unreg_x", ".3f")]))
    worst = max(r["rms_nm"] / r["bound_nm"] for r in rows)
    print(f"\nworst rms / bound: {worst:.2f}; axial ratio "
          f"{min(r['axial_x'] for r in rows):.3f} to {max(r['axial_x'] for r in rows):.3f}")


if __name__ == "__main__":
    main()
