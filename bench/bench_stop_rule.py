"""The 3D deblur's stopping rule (``stop=STOP_FIT`` with Biggs-Andrews acceleration, the
panel's default) against plain Richardson-Lucy of 50 iterations, on simulated volumes
from three generators of 3D PSFs:

* **ours**: :func:`~napari_psfspace.core.simulation.focus.simulate_focus_series`
  (``bench_volume.ours``, the moderate field at 512 x 512);
* **psfmodels** (code the project did not write): Gibson-Lanni vectorial PSFs under a
  tilted coverslip (``bench_volume.psfmodels_stack`` at 512 x 512);
* **pyotf** (code the project did not write): Hanser's vectorial pupil, NA 1.3 oil, with
  primary spherical aberration growing across the field (0 to 0.2 waves rms), 11 planes
  0.15 µm apart; its bead stack is its own field applied to beads on the middle plane.

For each, the 3D model is learnt from the bead stack; a 12 x 512 x 512 volume of points
and filaments (``bench_deblur3d.scene``) is blurred by the generator's *true* field
(``bench_deblur3d.true_operator``), with Poisson noise on a background of 20, then
deblurred with the learnt model by plain RL (50 iterations, the library's default) and by
the accelerated RL with the rule at each candidate threshold. Columns: the iterations the
rule ran, its result's relative l2 from plain RL's 50th iterate (``vs_rl50``), and each
result's error against the truth (relative l2 after a 1-voxel Gaussian and the best
scale, ``bench_deblur3d.region_error`` over the whole field; ``truth_ratio`` = the rule's
over plain RL's: at most 1 means the rule loses nothing against the truth).

    python bench/bench_stop_rule.py [--sets ours psfmodels pyotf] [--seeds 1 2]
        [--thresholds 1e-3 3e-3 1e-2] [--cap 25]

Needs the ``bench`` extra (pyotf, psfmodels).
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np

from bench_deblur3d import region_error, scene, true_operator
from bench_volume import ours, psfmodels_stack
from benchlib import table
from napari_psfspace.core.common.progress import run_with_progress
from napari_psfspace.core.volume import iter_estimate_operator_3d
from napari_psfspace.core.volume.deconvolve3d import STOP_FIT, richardson_lucy_3d
from napari_psfspace.core.volume.operator3d import ProductConvolution3D

SHAPE = (512, 512)
DEPTH = 12
BACKGROUND = 20.0


def pyotf_stack(seed: int, shape=SHAPE, n_beads: int = 25, dz: float = 0.15,
                planes: int = 11, size: int = 61):
    """A bead z-stack from pyotf's PSFs, spherical aberration growing with the column,
    made by the true field itself; returns what ``bench_volume``'s generators return."""
    from pyotf.otf import HanserPSF, apply_aberration

    from napari_psfspace.core.simulation.render import place_beads

    zv = dz * (np.arange(planes) - planes // 2)

    @functools.cache
    def column(xq: float) -> np.ndarray:
        model = HanserPSF(wl=600, na=1.3, ni=1.52, res=65, size=size,
                          zrange=list(zv * 1000), vec_corr="total", condition="sine")
        pcoefs = np.zeros(11)
        pcoefs[10] = 2 * np.pi * 0.2 * xq  # Noll 11, radians rms
        p = np.asarray(apply_aberration(model, None, pcoefs).PSFi, float)
        return p / p.sum(axis=(1, 2)).max()  # the brightest plane sums to 1

    def psf(y, x, n=size):
        p = column(round(float(x) / (shape[1] - 1), 2))  # a hundredth of the field
        c, h = size // 2, n // 2
        return p[:, c - h:c + h + 1, c - h:c + h + 1] if n < size else p

    rng = np.random.default_rng(seed)
    op = true_operator(psf, (planes, *shape), size, planes)
    beads = np.zeros((planes, *shape), np.float32)
    pos = place_beads(rng, shape, n_beads, 2.2 * 24, 35)
    beads[planes // 2, np.round(pos[:, 0]).astype(int), np.round(pos[:, 1]).astype(int)] = 2e4
    stack = rng.poisson(np.clip(op.apply(beads), 0, None) + 30.0).astype(np.uint16)
    return stack, psf, 24, 3


GENERATORS = {
    "ours": lambda seed: ours("moderate", seed),
    "psfmodels": lambda seed: psfmodels_stack(seed, shape=SHAPE, n_beads=25),
    "pyotf": pyotf_stack,
}


def run(name: str, seed: int, thresholds: list[float], cap: int | None = None
        ) -> list[dict]:
    stack, truth, radius, z_radius = GENERATORS[name](seed)
    est = run_with_progress(iter_estimate_operator_3d(stack, psf_radius=radius,
                                                      z_radius=z_radius)).operator
    h, w = stack.shape[1:]
    true_op = true_operator(truth, (DEPTH, h, w), est.kernel_shape[1], stack.shape[0])
    op = ProductConvolution3D(est.basis, est.coefficients, shape=(DEPTH, h, w),
                              grid=est.grid, plane=DEPTH // 2)
    obj = scene((DEPTH, h, w), 100 + seed)
    rng = np.random.default_rng(200 + seed)
    data = rng.poisson(np.clip(true_op.apply(obj), 0, None) + BACKGROUND).astype(np.float32)
    everywhere = np.ones((h, w), bool)
    t0 = time.perf_counter()
    plain = richardson_lucy_3d(data, op, n_iter=50, background=BACKGROUND)
    ref = plain.volume.astype(np.float64)
    base = region_error(plain.volume, obj, everywhere)
    rows = [{"set": name, "seed": seed, "method": "plain RL 50", "iterations": 50,
             "vs_rl50": 0.0, "truth": base, "truth_ratio": 1.0,
             "seconds": time.perf_counter() - t0}]
    runs = [(f"rule {t:g}", t, 50) for t in thresholds]
    if cap:
        runs.append((f"panel: rule {STOP_FIT:g}, at most {cap}", STOP_FIT, cap))
    for label, t, n in runs:
        t0 = time.perf_counter()
        res = richardson_lucy_3d(data, op, n_iter=n, background=BACKGROUND, stop=t,
                                 accelerate=True)
        err = region_error(res.volume, obj, everywhere)
        rows.append({"set": name, "seed": seed, "method": label,
                     "iterations": res.iterations,
                     "vs_rl50": float(np.linalg.norm(res.volume - ref) / np.linalg.norm(ref)),
                     "truth": err, "truth_ratio": err / base,
                     "seconds": time.perf_counter() - t0})
    print(table(rows, COLUMNS), flush=True)
    return rows


COLUMNS = [("set", "s"), ("seed", "d"), ("method", "s"), ("iterations", "d"),
           ("vs_rl50", ".4f"), ("truth", ".4f"), ("truth_ratio", ".3f"), ("seconds", ".1f")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", nargs="+", default=list(GENERATORS), choices=list(GENERATORS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--thresholds", nargs="*", type=float, default=[1e-3, STOP_FIT, 1e-2])
    ap.add_argument("--cap", type=int, default=None,
                    help="also the panel's run: the rule at STOP_FIT, at most CAP "
                         "iterations (the panel's PANEL_ITERATIONS is 25)")
    args = ap.parse_args()
    rows = []
    for name in args.sets:
        for seed in args.seeds:
            rows += run(name, seed, args.thresholds, args.cap)
    print(f"\nThe stopping rule against plain RL of 50 iterations (the library's STOP_FIT "
          f"is {STOP_FIT:g})")
    print(table(rows, COLUMNS))
    labels = [f"rule {t:g}" for t in args.thresholds]
    labels += [f"panel: rule {STOP_FIT:g}, at most {args.cap}"] if args.cap else []
    for label in labels:
        mine = [r for r in rows if r["method"] == label]
        print(f"{label}: iterations {min(r['iterations'] for r in mine)}-"
              f"{max(r['iterations'] for r in mine)}, vs_rl50 at most "
              f"{max(r['vs_rl50'] for r in mine):.4f}, truth_ratio at most "
              f"{max(r['truth_ratio'] for r in mine):.3f}")


if __name__ == "__main__":
    main()
