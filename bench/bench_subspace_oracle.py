"""What limits a family's operators: oracles on a simulated stack (issue 11).

    python bench/bench_subspace_oracle.py [--k 10] [--beads 24] [--seed 0]

On a stack of ``core/simulation/stacks.py`` (384 x 384, bead photons x0.2), the mean
per-image PSF-field error (aligned, 4 x 4 grid) of

- ``subspace``: the family's operators, ``subspace.operator(k)``;
- ``true_maps``: the *true* coefficient maps on the learnt PSF basis (the truth's PSFs at
  every grid node, projected onto the ``h_i``): the floor the basis sets, whatever the
  maps;
- ``true_maps_on_a``: those true maps projected onto the learnt spatial basis ``a_j``:
  the floor the ``a_j`` add.
"""

from __future__ import annotations

import argparse

import numpy as np

from benchlib import table
from napari_psfspace.core.family import estimate_family
from napari_psfspace.core.model.field import assemble_operator
from napari_psfspace.core.simulation.metrics import grid_errors
from napari_psfspace.core.simulation.stacks import simulate_stack


class Cached:
    """A truth whose PSFs are computed once per position."""

    def __init__(self, truth):
        self.truth, self.cache = truth, {}

    def psf_at(self, y, x, size):
        key = (y, x, size)
        if key not in self.cache:
            self.cache[key] = self.truth.psf_at(y, x, size)
        return self.cache[key]


def _operator(sub, coarse):
    """The operator of coarse maps (G, I) on the family's basis, grid and cone."""
    def field(nodes):
        return coarse
    return assemble_operator(sub.basis, sub.cone.generators, field, sub.shape,
                             grid_step=sub.grid_step)[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--beads", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    images, truths, _ = simulate_stack(args.k, (384, 384), args.beads, seed=args.seed,
                                       amplitude=(4e3, 1.2e4))
    r = int(np.median([t.psf_radius for t in truths]))
    cached = [Cached(t) for t in truths]
    sub = estimate_family(images, psf_radius=r, holdout=None)
    size = sub.basis.shape[1]
    nodes = np.stack(np.meshgrid(*sub.grid, indexing="ij"), -1).reshape(-1, 2)
    flat = sub.basis.reshape(sub.n_psf, -1)
    space = sub.space.reshape(sub.n_space, -1)
    rows = {"subspace": [], "true_maps": [], "true_maps_on_a": []}
    for k in range(args.k):
        rows["subspace"].append(np.mean(grid_errors(sub.operator(k), cached[k], n=4)))
        true_psfs = np.array([truths[k].psf_at(y, x, size) for y, x in nodes])
        coef = np.linalg.lstsq(flat.T, true_psfs.reshape(len(nodes), -1).T, rcond=None)[0].T
        rows["true_maps"].append(np.mean(grid_errors(_operator(sub, coef), cached[k], n=4)))
        on_a = ((coef.T @ space.T) @ space).T
        rows["true_maps_on_a"].append(np.mean(grid_errors(_operator(sub, on_a), cached[k],
                                                          n=4)))
    out = [{"K": args.k, "beads": args.beads, "I": sub.n_psf, "J": sub.n_space,
            **{key: float(np.mean(v)) for key, v in rows.items()}}]
    print(table(out, [("K", "d"), ("beads", "d"), ("I", "d"), ("J", "d"),
                      ("subspace", ".4f"), ("true_maps", ".4f"), ("true_maps_on_a", ".4f")]))


if __name__ == "__main__":
    main()
