"""Every path of the estimate and the diagnosis on damaged scenes: a model or a message.

Scenes of the family (:func:`random_scene`: 8/12/16-bit, 3-80 beads, the radius the
simulator gives or one from 3 px to twice it), each plain or damaged
(:mod:`napari_psfspace.core.simulation.damage`: clipped to the floor, saturated, a flat
background, stray counts, a constant block). Each run of :func:`estimate_operator` and
:func:`diagnose` ends with a model, with one of the project's errors
(:class:`PsfSpaceError`, a message), or UNCAUGHT: a bug, a NaN or an infinity reaching
a solver of numpy or scipy included (they only print a LAPACK warning). Prints the table
of outcomes and every uncaught exception.

    python bench/bench_fuzz.py [--scenes 60]
"""

from __future__ import annotations

import argparse
import time
import traceback

import numpy as np

from benchlib import table
from napari_psfspace.core.common.errors import PsfSpaceError
from napari_psfspace.core.diagnosis.loop import diagnose
from napari_psfspace.core.model.estimate import estimate_operator
from napari_psfspace.core.simulation.damage import DAMAGES, damaged
from napari_psfspace.core.simulation.scene_set import random_scene


class NonFiniteInput(RuntimeError):
    """A NaN or infinity reached a linear-algebra routine (LAPACK only prints a warning
    and returns garbage): a NaN returned silently, somewhere upstream."""


def _strict_linear_algebra() -> None:
    """Make numpy's and scipy's solvers raise :class:`NonFiniteInput` on non-finite
    input, so that the fuzz counts it as a bug."""
    import numpy.linalg as nl
    import scipy.linalg as sl

    def guard(module, name):
        fn = getattr(module, name)

        def checked(*args, **kwargs):
            for a in args[:2]:
                if isinstance(a, np.ndarray) and a.dtype.kind in "fc" and not np.all(
                        np.isfinite(a)):
                    raise NonFiniteInput(f"non-finite input to {module.__name__}.{name}")
            return fn(*args, **kwargs)

        setattr(module, name, checked)

    for name in ("lstsq", "svd", "eigh", "solve", "pinv", "inv"):
        guard(nl, name)
    for name in ("eigh", "solve_triangular", "lstsq", "solve"):
        guard(sl, name)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=60)
    args = ap.parse_args()
    _strict_linear_algebra()
    counts: dict[tuple[str, str], dict[str, int]] = {}
    bugs = []
    t0 = time.perf_counter()
    seed, done = -1, 0
    while done < args.scenes:
        seed += 1
        try:
            image, truth, p = random_scene(seed, shape=(256, 256), n_beads=(3, 80))
        except ValueError:
            continue
        done += 1
        rng = np.random.default_rng(1000 + seed)
        r = float(rng.choice([3.0, truth.psf_radius, truth.psf_radius * rng.uniform(0.5, 2)]))
        kind = seed % len(DAMAGES)
        img = damaged(image, kind, seed)
        for name, run in (("estimate", lambda img=img, r=r: estimate_operator(
                                img, psf_radius=r)),
                          ("diagnose", lambda img=img, r=r: diagnose(img, psf_radius=r,
                                                                     max_steps=3))):
            key = (name, DAMAGES[kind])
            c = counts.setdefault(key, {"model": 0, "stopped": 0, "UNCAUGHT": 0})
            try:
                run()
                c["model"] += 1
            except PsfSpaceError:
                c["stopped"] += 1
            except Exception as exc:  # noqa: BLE001 - what this bench looks for
                c["UNCAUGHT"] += 1
                bugs.append(f"seed {seed} ({DAMAGES[kind]}, r {r:.3g}, {p['bits']}-bit) "
                            f"{name}: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
    rows = [{"run": k[0], "damage": k[1], **v} for k, v in sorted(counts.items())]
    print(f"{done} scenes (256 x 256) in {time.perf_counter() - t0:.0f} s")
    print(table(rows, [("run", "s"), ("damage", "s"), ("model", "d"), ("stopped", "d"),
                       ("UNCAUGHT", "d")]))
    for b in bugs:
        print(b)
    print(f"{len(bugs)} uncaught exception(s)")


if __name__ == "__main__":
    main()
