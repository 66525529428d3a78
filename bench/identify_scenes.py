"""Scenes of the identification benches: a family learnt from one microscope under hidden
conditions, and new images to identify, inside the range learnt or beyond it.

The hidden conditions are a focus and a tilt of the slide (defocus growing across the
field in y and in x), drawn uniformly in ``[-1, 1]^3`` (normalised coordinates) and
scaled by ``SPREADS[name]`` (waves rms: the simulator's default spread of
``core/simulation/stacks.CONDITIONS``, "default", or a wider one): ``K`` training images,
then test images *inside* the box the training conditions span (every coordinate within
their range) or *beyond* it (some coordinate outside, all within 1.5 times the spread).
Every image is 150 beads on ``size`` x ``size`` pixels by default, as the issue's
measurement; the PSFs come from our simulator, pyotf or psfmodels (``bench/independent.py``).

Rendering with pyotf or psfmodels takes about 25 s an image of 1024 x 1024 with 150
beads: ``--cache DIR`` keeps each scene's images and truths (``.npz`` of arrays, the
truths rebuilt from their parameters) so that benches share them.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchlib import optics_type
from napari_psfspace.core.simulation.aberrations import PRESETS, FieldAberrations
from napari_psfspace.core.simulation.stacks import Condition, simulate_stack

#: Spread of each condition (waves rms): the focus shift, and the tilt (defocus per unit
#: of the field's normalised coordinate, -1 to 1 across the image).
SPREADS = {"default": {"focus": 0.12, "tilt": 0.05}, "wide": {"focus": 0.2, "tilt": 0.1}}


def conditions(z: np.ndarray, spread: dict) -> list[Condition]:
    """Conditions of normalised coordinates ``z`` (n, 3): focus, tilt in y, tilt in x."""
    return [Condition(float(f) * spread["focus"], float(tx) * spread["tilt"],
                      float(ty) * spread["tilt"], 0.0) for f, ty, tx in np.atleast_2d(z)]


def draw_tests(rng, z_train: np.ndarray, n: int, beyond: bool) -> np.ndarray:
    """``n`` normalised conditions inside the box of ``z_train`` (or, ``beyond``, outside
    it on some coordinate and within 1.5 on all)."""
    lo, hi = z_train.min(axis=0), z_train.max(axis=0)
    out = []
    for _ in range(100000):
        if len(out) == n:
            break
        z = rng.uniform(-1.5, 1.5, 3) if beyond else rng.uniform(lo, hi)
        inside = bool(np.all((z >= lo) & (z <= hi)))
        if inside != beyond:
            out.append(z)
    return np.array(out)


@dataclass
class Scene:
    """One seed's family scene."""

    z_train: np.ndarray
    train: list
    train_truths: list
    z_test: np.ndarray
    beyond: np.ndarray  # (n_test,) bool
    tests: list
    test_truths: list
    psf_radius: int


def _optics(generator: str):
    if generator == "ours":
        return None
    return optics_type(generator)(na=1.3, wavelength=0.6, pixel_size=0.065)


def make_scene(seed: int, *, generator: str = "ours", spread: str = "default",
               k: int = 10, n_inside: int = 3, n_beyond: int = 2, size: int = 1024,
               beads: int = 150, cache: str | None = None) -> Scene:
    """The scene of ``seed`` (its images rendered, or read from ``cache``)."""
    rng = np.random.default_rng([seed, 63])
    z_train = rng.uniform(-1, 1, (k, 3))
    z_in = draw_tests(rng, z_train, n_inside, False)
    z_out = draw_tests(rng, z_train, n_beyond, True)
    z_test = np.vstack([z_in, z_out]) if n_beyond else z_in
    beyond = np.r_[np.zeros(len(z_in), bool), np.ones(len(z_out), bool)]
    key = dict(seed=seed, generator=generator, spread=spread, k=k, n_inside=n_inside,
               n_beyond=n_beyond, size=size, beads=beads)
    path = None
    if cache:
        tag = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
        path = Path(cache) / f"scene_{generator}_{seed}_{tag}.npz"
    sp = SPREADS[spread]
    optics = _optics(generator)
    kwargs = {"optics": optics}
    shape = (size, size)
    if path is not None and path.exists():
        data = np.load(path)
        train, tests = list(data["train"]), list(data["tests"])
        train_truths = _truths(data, "train", conditions(z_train, sp), shape, beads, seed,
                               optics)
        test_truths = _truths(data, "tests", conditions(z_test, sp), shape, beads,
                              seed + 1000, optics)
    else:
        train, train_truths, _ = simulate_stack(k, shape, beads, seed=seed,
                                                conditions=conditions(z_train, sp), **kwargs)
        tests, test_truths, _ = simulate_stack(len(z_test), shape, beads, seed=seed + 1000,
                                               conditions=conditions(z_test, sp), **kwargs)
        if path is not None:
            os.makedirs(path.parent, exist_ok=True)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, train=np.array(train), tests=np.array(tests),
                     **_positions("train", train_truths), **_positions("tests", test_truths))
            os.replace(tmp, path)
    r = int(np.median([t.psf_radius for t in train_truths]))
    return Scene(z_train, train, train_truths, z_test, beyond, tests, test_truths, r)


def _positions(name, truths) -> dict:
    """The truths' bead positions as plain arrays: all of them, and each image's count."""
    return {f"{name}_pos": np.concatenate([t.positions for t in truths]),
            f"{name}_count": np.array([len(t.positions) for t in truths])}


def _truths(data, name, conds, shape, beads, seed, optics):
    """The truths of cached images: the same simulation with its noise, redone only for
    its parameters (positions, aberrations) at no rendering cost: the images are read."""
    out = []
    base = FieldAberrations(PRESETS["moderate"])
    ends = np.cumsum(data[f"{name}_count"])
    pos = np.split(data[f"{name}_pos"], ends[:-1])
    for i, c in enumerate(conds):
        out.append(_truth_of(c.aberrations(base), shape, optics, pos[i]))
    return out


def _truth_of(aberrations, shape, optics, positions):
    """A truth object for the PSFs only (``psf_at``, ``positions``, ``psf_radius``)."""
    from napari_psfspace.core.simulation.optics import Optics, field_psf_radius
    from napari_psfspace.core.simulation.truth import SimulationTruth

    optics = Optics() if optics is None else optics
    r = field_psf_radius(aberrations, optics, shape)
    n = len(positions)
    return SimulationTruth(shape=shape, positions=np.asarray(positions, float),
                           amplitudes=np.ones(n), background=np.zeros(1), optics=optics,
                           aberrations=aberrations, gain=1.0, offset=0.0, read_noise=0.0,
                           psf_radius=int(r), peak_snr=np.ones(n))


class Cached:
    """A truth whose PSFs are computed once per position and size (pyotf's are slow)."""

    def __init__(self, truth):
        self.truth = truth
        self.positions, self.psf_radius = truth.positions, truth.psf_radius
        self.shape = truth.shape
        self._store = {}

    def psf_at(self, y, x, size=None):
        key = (round(float(y), 3), round(float(x), 3), size)
        if key not in self._store:
            self._store[key] = self.truth.psf_at(y, x, size)
        return self._store[key]


def inner(positions: np.ndarray, shape, r: float) -> np.ndarray:
    """The positions at least ``r`` from the border (a bead a user can click)."""
    h, w = shape
    ok = ((positions[:, 0] >= r) & (positions[:, 0] <= h - 1 - r)
          & (positions[:, 1] >= r) & (positions[:, 1] <= w - 1 - r))
    return positions[ok]


def spread_picks(positions: np.ndarray, shape, r: float, p: int) -> np.ndarray:
    """``p`` positions well spread over the field (farthest points from the one nearest
    the centre), among those at least ``r`` from the border."""
    pts = inner(positions, shape, r)
    h, w = shape
    first = int(np.argmin(np.hypot(pts[:, 0] - h / 2, pts[:, 1] - w / 2)))
    picks = [first]
    d = np.hypot(*(pts - pts[first]).T)
    while len(picks) < min(p, len(pts)):
        nxt = int(np.argmax(d))
        picks.append(nxt)
        d = np.minimum(d, np.hypot(*(pts - pts[nxt]).T))
    return pts[picks]
