"""Best focus on high-NA stacks whose beads are rings a micrometre out of focus.

At NA 1.3-1.49 a bead 1 µm out of focus is a ring a few pixels across, as bright in
total as the spot in focus and, on a slice, often of higher contrast. The best focus
must be the slice where the beads are sharpest: the **truth** here is the slice of the
highest median bead peak on the noise-free stack (each bead's peak within 1.5 px of its
true centre). Judged: :func:`best_focus_index` on the noisy stack (within one frame),
and the bead plane of :func:`estimate_operator_3d` (within one frame), for several PSF
radii (the focus must not follow the radius).

PSFs from **pyotf** and **psfmodels** (the ``bench`` extra; ``bench_fwhm_reference``'s
``simulated_psf``), ideal and through a refractive-index mismatch (pyotf: 0.15 waves of
spherical aberration; psfmodels: an oil objective 3 µm into water), where one side of
focus is a compact bright tail: planes 0.1 µm apart over +- 1.5 µm, 65 nm pixels, 0.6 µm light;
a field of 36 beads at random sub-pixel phases and brightness (5e3-2e4 photons), a
background of 20, Poisson noise; seeds change the layout, phases, brightness and noise.

    python bench/bench_focus_rings.py [--seeds 10] [--na 1.3 1.4 1.49]
"""

from __future__ import annotations

import argparse

import numpy as np

from bench_fwhm_reference import simulated_psf
from benchlib import table
from napari_psfspace.core.beads.focus import bead_peaks, best_focus_index
from napari_psfspace.core.volume import estimate_operator_3d


def ring_stack(fine, q: int, size: int, nz: int, seed: int):
    """A noisy stack of 36 beads with the PSF ``fine`` (the stack's planes, laterally q
    times finer than the pixels), the clean stack and the beads' centres."""
    rng = np.random.default_rng(seed)
    shape = (nz, 288, 288)
    clean = np.full(shape, 20.0)
    half = size // 2
    centres = []
    for y in range(30, 260, 40):
        for x in range(30, 260, 40):
            py, px = rng.integers(0, q, 2)
            y0, x0 = y + int(rng.integers(-4, 5)), x + int(rng.integers(-4, 5))
            sl = np.roll(fine[:nz], (py - q // 2, px - q // 2), axis=(1, 2))
            binned = sl.reshape(len(sl), size, q, size, q).sum(axis=(2, 4))
            clean[:, y0 - half:y0 + half + 1, x0 - half:x0 + half + 1] += (
                rng.uniform(5e3, 2e4) * binned / binned.sum(axis=(1, 2)).max())
            centres.append((y0 - (py - q // 2) / q, x0 - (px - q // 2) / q))
    return rng.poisson(clean).astype(np.float32), clean, np.array(centres)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--na", type=float, nargs="+", default=[1.3, 1.4, 1.49])
    ap.add_argument("--radii", type=float, nargs="+", default=[8, 14, 20])
    args = ap.parse_args()
    q, size, nz, dz = 5, 45, 31, 0.1
    rows = []
    for gen, mismatch in (("pyotf", False), ("pyotf", True), ("psfmodels", False),
                          ("psfmodels", True)):
        for na in args.na:
            fine, _, _ = simulated_psf(gen, na, 0.6, 0.065, dz, nz, q, size, mismatch)
            fine = fine[::q]  # the stack's planes, laterally still q times finer
            for seed in range(args.seeds):
                noisy, clean, centres = ring_stack(fine, q, size, nz, seed)
                med = np.median(bead_peaks(clean, centres, 10.0), axis=0)
                truth = int(np.argmax(med))
                got = best_focus_index(noisy)
                planes = []
                for r in args.radii:
                    op = estimate_operator_3d(noisy, psf_radius=r, holdout=False)
                    planes.append(op.plane)
                ring = float(med[max(truth - 10, 0)] / med[truth])
                rows.append({"generator": gen + (" mismatch" if mismatch else ""),
                             "NA": na, "seed": seed, "truth": truth,
                             "best_focus": got, "off": got - truth,
                             "bead_plane": " ".join(str(p) for p in planes),
                             "plane_off": max(abs(p - truth) for p in planes),
                             "peak_1um_out": ring})
    print(table(rows, [("generator", "s"), ("NA", ".2f"), ("seed", "d"), ("truth", "d"),
                       ("best_focus", "d"), ("off", "d"), ("bead_plane", "s"),
                       ("plane_off", "d"), ("peak_1um_out", ".2f")]))
    off = np.array([abs(r["off"]) for r in rows])
    poff = np.array([r["plane_off"] for r in rows])
    print(f"\n{len(rows)} stacks: best focus within one frame on {int((off <= 1).sum())}, "
          f"bead plane (radii {args.radii}) within one frame on {int((poff <= 1).sum())}")


if __name__ == "__main__":
    main()
