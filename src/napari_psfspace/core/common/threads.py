"""Row-block parallelism for work that releases the GIL (numpy element-wise operations,
``scipy.ndimage`` filters), on one shared pool of threads.

Between two FFTs, or while one filter runs, the other cores of a laptop are idle; numpy
and ``scipy.ndimage`` release the GIL, so splitting an image into blocks of rows runs
them in parallel without copying it to other processes.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def default_workers() -> int:
    """Threads to use by default: the machine's cores."""
    return os.cpu_count() or 1


def _pool(workers: int) -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL._max_workers < workers:
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="psfspace")
        return _POOL


def by_rows(fn: Callable, arrays: tuple[np.ndarray, ...], workers: int) -> None:
    """Run ``fn(*blocks)`` on ``workers`` row blocks of the arrays, in parallel threads.

    Element-wise numpy operations release the GIL, and between two FFTs the cores are
    otherwise idle: on 2 cores this halves the element-wise part of ``apply`` (measured
    on 2400 x 1201 complex64: multiply-accumulate 9.4 -> 4.6 ms).
    """
    n = arrays[0].shape[0]
    if workers <= 1 or n < 256:
        fn(*arrays)
        return
    pool = _pool(workers)
    edges = np.linspace(0, n, workers + 1).astype(int)
    futures = [pool.submit(fn, *(a[lo:hi] for a in arrays))
               for lo, hi in zip(edges[1:-1], edges[2:], strict=True)]
    fn(*(a[edges[0]:edges[1]] for a in arrays))
    for f in futures:
        f.result()


def filter_by_rows(fn: Callable[[np.ndarray], np.ndarray], image: np.ndarray, halo: int,
                   workers: int | None = None) -> np.ndarray:
    """``fn(image)`` for a neighbourhood filter reaching ``halo`` rows, on row blocks in
    parallel threads; the same result as one call (each block is filtered with ``halo``
    rows of its neighbours, the image's own edges keep the filter's boundary mode).

    Measured: a Laplacian of Gaussian of 2304 x 2304 float32 (sigma 5.5) 418 -> 256 ms on
    2 cores, bit-identical.
    """
    workers = default_workers() if workers is None else int(workers)
    n = image.shape[0]
    if workers <= 1 or n < 4 * max(halo, 64):
        return fn(image)
    pool = _pool(workers)
    edges = np.linspace(0, n, workers + 1).astype(int)

    def block(lo: int, hi: int) -> np.ndarray:
        a, b = max(0, lo - halo), min(n, hi + halo)
        return fn(image[a:b])[lo - a:lo - a + hi - lo]

    futures = [pool.submit(block, lo, hi) for lo, hi in zip(edges[1:-1], edges[2:],
                                                              strict=True)]
    first = block(edges[0], edges[1])
    return np.concatenate([first, *(f.result() for f in futures)], axis=0)
