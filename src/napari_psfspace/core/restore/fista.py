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

Blocks = list[np.ndarray]


class BlockFista:
    """Accelerated proximal gradient over blocks.

    Parameters
    ----------
    gradient : callable
        ``gradient(x: Blocks) -> (grad: Blocks, smooth_value: float)``: the gradient of
        ``f`` and ``f`` itself at ``x``.
    prox : sequence of callables
        ``prox[b](v, step) -> ndarray``: the proximal map of ``step * g_b`` (may work in
        place on ``v``).
    lipschitz : sequence of float
        ``L_b`` of each block (> 0).
    penalty : callable, optional
        ``penalty(x) -> float``: ``g(x)``, for the objective history.
    """

    def __init__(self, gradient: Callable[[Blocks], tuple[Blocks, float]],
                 prox: Sequence[Callable[[np.ndarray, float], np.ndarray]],
                 lipschitz: Sequence[float],
                 penalty: Callable[[Blocks], float] | None = None) -> None:
        if len(prox) != len(lipschitz):
            raise ValueError("`prox` and `lipschitz` must have one entry per block")
        if any(not (np.isfinite(v) and v > 0) for v in lipschitz):
            raise ValueError(f"`lipschitz` must be positive, got {list(lipschitz)}")
        self.gradient, self.prox = gradient, list(prox)
        self.lipschitz = [float(v) for v in lipschitz]
        self.penalty = penalty
        self.x: Blocks = []
        self.objective: list[float] = []
        self.restarts = 0
        self.iterations = 0

    def setup(self, x0: Blocks) -> None:
        """Start from ``x0`` (copied)."""
        self.x = [np.array(b, copy=True) for b in x0]
        self.z = [b.copy() for b in self.x]  # extrapolated point
        self.t = 1.0
        self.objective, self.restarts, self.iterations = [], 0, 0

    def step(self) -> float:
        """One iteration; returns ``||x_new - x|| / ||x_new||`` over all blocks."""
        grad, fz = self.gradient(self.z)
        if self.penalty is not None:
            self.objective.append(float(fz) + float(self.penalty(self.z)))
        new, steps = [], []
        for b, (z, g) in enumerate(zip(self.z, grad, strict=True)):
            step = 1.0 / self.lipschitz[b]
            g *= -step  # in place: the gradient is not needed again
            g += z
            new.append(self.prox[b](g, step))
            steps.append(new[-1] - self.x[b])  # x_new - x
        change = sum(float(np.vdot(d, d)) for d in steps)
        norm = sum(float(np.vdot(n, n)) for n in new)
        # gradient restart: the step x_new - x points against the momentum's direction
        against = sum(float(np.vdot(z, d)) - float(np.vdot(n, d))
                      for z, n, d in zip(self.z, new, steps, strict=True))
        if against > 0:
            self.t = 1.0
            self.restarts += 1
        # a Python float: a NumPy float64 would turn float32 blocks into float64 (NEP 50)
        t_new = 0.5 * (1.0 + float(np.sqrt(1.0 + 4.0 * self.t * self.t)))
        beta = (self.t - 1.0) / t_new
        for d, n in zip(steps, new, strict=True):  # z = x_new + beta (x_new - x), in place
            d *= beta
            d += n
        self.z = steps
        self.x, self.t = new, t_new
        self.iterations += 1
        return float(np.sqrt(change / max(norm, 1e-300)))

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
