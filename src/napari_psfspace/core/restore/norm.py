"""``||H||^2`` of a 2-D operator by power iteration: the step of the deblur's gradient
iterations."""

from __future__ import annotations

from collections.abc import Generator

import numpy as np

from ..common.device import CPU, ArrayModule, array_module
from ..common.twins import drained
from ..model.operator import ProductConvolution


def iter_operator_norm2(op: ProductConvolution, *, n_iter: int = 40, rtol: float = 1e-3,
                        seed: int = 0, workers: int | None = None,
                        device: str | ArrayModule = CPU
                        ) -> Generator[tuple[int, float], None, float]:
    """``||H||^2`` by power iteration on ``H^T H`` (a lower bound, converging from
    below).

    Parameters
    ----------
    op : ProductConvolution
        The operator ``H``.
    n_iter : int
        Iterations at most.
    rtol : float
        Stop once an iteration raises the value by less than this, relatively.
    seed : int
        Seed of the random start.
    workers : int, optional
        FFT threads.
    device : {"auto", "cpu", "gpu"} or ArrayModule
        Where ``H`` runs (:mod:`~napari_psfspace.core.common.device`).

    Yields
    ------
    (int, float)
        The iteration and the value after it (a point to cancel at: one application
        of ``H^T H`` apart).

    Returns
    -------
    float
        ``||H||^2``.
    """
    device = array_module(device)
    rng = np.random.default_rng(seed)
    x = rng.random(op.image_shape).astype(np.float32)
    x /= np.linalg.norm(x)
    value = 0.0
    for it in range(int(n_iter)):
        y = device.to_host(op.adjoint(op.apply(x, workers=workers, device=device),
                                      workers=workers, device=device))
        new = float(np.linalg.norm(y))
        if new == 0:
            return 0.0
        x = (y / new).astype(np.float32)
        done = abs(new - value) <= rtol * new
        value = new
        yield it + 1, value
        if done:
            break
    return value


operator_norm2 = drained(iter_operator_norm2, "operator_norm2", result=float)


__all__ = ["iter_operator_norm2", "operator_norm2"]
