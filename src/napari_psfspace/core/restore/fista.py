"""FISTA for ``min f(x) + g(x)`` over blocks of variables, in pylops' solver pattern.

``f`` is smooth; its gradient is majorised block by block (``f(x + d) <= f(x) + <grad,
d> + sum_b L_b / 2 ||d_b||^2``), so that each block takes its own step ``1 / L_b``: the
method is FISTA in the diagonal metric ``diag(L_b)``, with the same guarantees. ``g`` is
separable over the blocks, with a simple proximal map per block.

Like pylops' solvers (``setup`` / ``step`` / ``run`` / ``finalize``): ``setup`` takes the
start point, ``step`` does one iteration and returns the relative change, ``run`` is a
generator of the iteration count (so that a caller can report progress and stop between
iterations). Momentum restarts when the step goes against it (O'Donoghue and Candes'
gradient scheme), which costs nothing and removes FISTA's oscillations on strongly convex
parts.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Sequence

import numpy as np

from ..common.device import namespace
from ..common.threads import default_workers, map_rows

Blocks = list[np.ndarray]


class BlockFista:
    """Accelerated proximal gradient over blocks.

    Parameters
    ----------
    gradient : callable
        ``gradient(x: Blocks) -> (grad: Blocks, smooth_value: float)``: the gradient of
        ``f`` and ``f`` itself at ``x``. The solver overwrites the returned gradients.
    prox : sequence of callables
        ``prox[b](v, step, rows) -> ndarray``: the proximal map of ``step * g_b`` at
        ``v = block[rows]``, a slice of the block's first axis (the map must be
        separable along it; it may work in place on ``v``).
    lipschitz : sequence of float
        ``L_b`` of each block (> 0).
    penalty : sequence of callables or None, optional
        ``penalty[b](x_rows, rows) -> float``: ``g_b`` on a slice of rows of block
        ``b`` (None: 0), for the objective history.
    workers : int, optional
        Threads for the element-wise work (default: the machine's cores).

    Notes
    -----
    An iteration's element-wise work (gradient step, proximal map, the sums of the
    restart test and of the objective, the extrapolation) runs fused on chunks of
    rows in threads: two passes over each block instead of a dozen
    (``bench/bench_deblur_speed.py``). Blocks on a GPU (CuPy arrays, from ``setup``)
    stay there, and each step runs on a whole block at once (``rows`` is then
    ``slice(None)``).
    """

    def __init__(self, gradient: Callable[[Blocks], tuple[Blocks, float]],
                 prox: Sequence[Callable[[np.ndarray, float, slice], np.ndarray]],
                 lipschitz: Sequence[float],
                 penalty: Sequence[Callable[[np.ndarray, slice], float] | None]
                 | None = None, *, workers: int | None = None) -> None:
        if len(prox) != len(lipschitz):
            raise ValueError("`prox` and `lipschitz` must have one entry per block")
        if any(not (np.isfinite(v) and v > 0) for v in lipschitz):
            raise ValueError(f"`lipschitz` must be positive, got {list(lipschitz)}")
        if penalty is not None and len(penalty) != len(prox):
            raise ValueError("`penalty` must have one entry (or None) per block")
        self.gradient, self.prox = gradient, list(prox)
        self.lipschitz = [float(v) for v in lipschitz]
        self.penalty = None if penalty is None else list(penalty)
        self.workers = default_workers() if workers is None else int(workers)
        self.xp = np  # the blocks' array module, from setup
        self.x: Blocks = []
        self.objective: list[float] = []
        self.restarts = 0
        self.iterations = 0

    def setup(self, x0: Blocks) -> None:
        """Start from ``x0`` (copied; the blocks stay on the device they are on)."""
        self.xp = namespace(x0[0])
        self.x = [self.xp.array(b, copy=True) for b in x0]
        self.z = [b.copy() for b in self.x]  # extrapolated point
        self.t = 1.0
        self.objective, self.restarts, self.iterations = [], 0, 0

    def _map(self, fn: Callable[[slice], object], block: np.ndarray) -> list:
        if self.xp is not np:  # a device: one call on the whole block
            return [fn(slice(None))]
        return map_rows(fn, block.shape[0], self.workers)

    def step(self) -> float:
        """One iteration; returns ``||x_new - x|| / ||x_new||`` over all blocks."""
        grad, fz = self.gradient(self.z)
        sums = np.zeros(4)  # ||d||^2, ||x_new||^2, <z - x_new, d>, penalty at z
        xp = self.xp
        for b, (z, g, x) in enumerate(zip(self.z, grad, self.x, strict=True)):
            step = 1.0 / self.lipschitz[b]
            prox = self.prox[b]
            pen = None if self.penalty is None else self.penalty[b]

            def forward(rows, z=z, g=g, x=x, step=step, prox=prox, pen=pen):
                zr, gr, xr = z[rows], g[rows], x[rows]
                gr *= -step  # in place: the gradient is not needed again
                gr += zr
                new = prox(gr, step, rows)
                if new is not gr:
                    gr[...] = new
                xp.subtract(gr, xr, out=xr)  # the old iterate's buffer now holds d
                zd = float(xp.vdot(zr, xr)) - float(xp.vdot(gr, xr))
                return (float(xp.vdot(xr, xr)), float(xp.vdot(gr, gr)), zd,
                        0.0 if pen is None else float(pen(zr, rows)))

            sums += np.sum(self._map(forward, z), axis=0)
        if self.penalty is not None:
            self.objective.append(float(fz) + float(sums[3]))
        # gradient restart: the step x_new - x points against the momentum's direction
        if sums[2] > 0:
            self.t = 1.0
            self.restarts += 1
        # a Python float: a NumPy float64 would turn float32 blocks into float64 (NEP 50)
        t_new = 0.5 * (1.0 + float(np.sqrt(1.0 + 4.0 * self.t * self.t)))
        beta = (self.t - 1.0) / t_new
        for z, new, d in zip(self.z, grad, self.x, strict=True):
            def extrapolate(rows, z=z, new=new, d=d):  # z = x_new + beta d, in place
                xp.multiply(d[rows], beta, out=z[rows])
                z[rows] += new[rows]

            self._map(extrapolate, z)
        self.x, self.t = list(grad), t_new
        self.iterations += 1
        return float(np.sqrt(float(sums[0]) / max(float(sums[1]), 1e-300)))

    def run(self, max_iter: int, tol: float, *, window: int = 10
            ) -> Generator[tuple[int, float], None, bool]:
        """Iterate; yields ``(iteration, relative change of the iterate)``; returns True
        when the least objective so far fell by less than ``tol`` (relatively) over the
        last ``window`` iterations (with no ``penalty``: when the iterate's relative
        change fell below ``tol``).

        The objective's decrease is the steadier rule: with momentum the iterate's
        change jumps by orders of magnitude from one iteration to the next, and the
        objective itself is not monotone (hence its running minimum).
        """
        best: list[float] = []
        for _ in range(int(max_iter)):
            change = self.step()
            yield self.iterations, change
            if self.penalty is None:
                if change < tol:
                    return True
                continue
            value = self.objective[-1]
            best.append(min(best[-1], value) if best else value)
            if len(best) > window and best[-1 - window] - best[-1] <= tol * abs(best[-1]):
                return True
        return False

    def finalize(self) -> Blocks:
        """The last iterate."""
        return self.x
