"""Row-block parallelism for work that releases the GIL (numpy element-wise operations,
``scipy.ndimage`` filters), on one shared pool of threads.

Between two FFTs, or while one filter runs, the other cores of a laptop are idle; numpy
and ``scipy.ndimage`` release the GIL, so splitting an image into blocks of rows runs
them in parallel without copying it to other processes.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

#: Threads BLAS and LAPACK may use while the package's estimates run (None: as the
#: process has them). The estimates' linear algebra is many small SVDs and
#: eigendecompositions (patches, thin-plate kernels of a few hundred beads) run from
#: several threads at once; OpenBLAS's own threads on top of them made learning slower,
#: not faster ("BLAS threads"). ``PSFSPACE_BLAS_THREADS`` in the
#: environment overrides it (0: leave BLAS as it is).
BLAS_THREADS: int | None = 1

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def default_workers() -> int:
    """Threads to use by default: the machine's cores."""
    return os.cpu_count() or 1


def dask_workers() -> int:
    """Threads for a local dask compute: dask's ``num_workers`` setting, else the cores
    dask counts (``dask.system.CPU_COUNT``). Named on every compute: from a thread other
    than the main one, dask's threads scheduler would otherwise make a pool of Python's
    default size (cores + 4)."""
    import dask
    from dask.system import CPU_COUNT

    return int(dask.config.get("num_workers", None) or CPU_COUNT)


def compute_tasks(tasks: list, client) -> list:
    """dask ``tasks`` computed: on ``client`` (a dask.distributed Client), else on the
    local threads scheduler with :func:`dask_workers` threads."""
    import dask

    if client is not None:
        return list(client.gather(client.compute(tasks)))
    # the workers named (dask's setting, else the cores): called from a thread other than
    # the main one (Cancel, wait_with_progress), dask's threads scheduler would otherwise
    # make a pool of Python's default size (cores + 4), oversubscribing the cores
    return list(dask.compute(*tasks, scheduler="threads", num_workers=dask_workers()))


def compute_first(first, rest: list, client) -> list:
    """``[first, *rest]`` computed, ``first`` (the longest task) started at once.

    dask's local threads scheduler orders independent tasks its own way and may start the
    longest last, after every short one: locally ``first`` therefore runs in a thread of
    its own while the others share the remaining workers (one at least)."""
    if client is not None or dask_workers() < 2 or not rest:
        return compute_tasks([first, *rest], client)
    import dask

    with ThreadPoolExecutor(1) as pool:
        head = pool.submit(dask.compute, first, scheduler="sync")
        tail = list(dask.compute(*rest, scheduler="threads", num_workers=dask_workers() - 1))
        return [head.result()[0], *tail]


def blas_limit():
    """A context in which BLAS runs on :data:`BLAS_THREADS` threads: where the work
    already runs on threads of its own (blocks, tiles), OpenBLAS's threads would compete
    with them for the cores."""
    return _blas_limit()


def _blas_limit():
    """A context in which BLAS runs on :data:`BLAS_THREADS` threads (threadpoolctl; a
    no-op where it is missing or no limit is asked)."""
    n = BLAS_THREADS
    env = os.environ.get("PSFSPACE_BLAS_THREADS", "").strip()
    if env:
        try:
            n = int(env) or None
        except ValueError:
            raise ValueError(f"PSFSPACE_BLAS_THREADS must be a whole number of threads "
                             f"(0: leave BLAS as it is), got {env!r}") from None
    if n is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover (a dependency; kept working without it)
        return contextlib.nullcontext()
    return threadpool_limits(limits=int(n), user_api="blas")


def blas_threads(fn: Callable) -> Callable:
    """Run ``fn`` (a function, or a generator function for its whole iteration) with
    BLAS limited to :data:`BLAS_THREADS` threads, then give BLAS back its threads.

    The limit is the process's (BLAS has no per-thread setting): other work running
    meanwhile shares it. Nested calls keep the outer limit.
    """
    if inspect.isgeneratorfunction(fn):
        @functools.wraps(fn)
        def generator(*args, **kwargs):
            with _blas_limit():
                return (yield from fn(*args, **kwargs))
        return generator

    @functools.wraps(fn)
    def function(*args, **kwargs):
        with _blas_limit():
            return fn(*args, **kwargs)
    return function


def _pool(workers: int) -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL._max_workers < workers:
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="psfspace")
        return _POOL


def map_threads(fn: Callable, items: list, workers: int | None = None) -> list:
    """``[fn(x) for x in items]`` on the shared pool of threads (in order); for work
    that spends its time in numpy's and LAPACK's GIL-free calls."""
    workers = default_workers() if workers is None else int(workers)
    if workers <= 1 or len(items) < 2:
        return [fn(x) for x in items]
    return list(_pool(workers).map(fn, items))


def by_rows(fn: Callable, arrays: tuple[np.ndarray, ...], workers: int) -> None:
    """Run ``fn(*blocks)`` on ``workers`` row blocks of the arrays, in parallel threads.

    Element-wise numpy operations release the GIL, and between two FFTs the cores are
    otherwise idle: the element-wise part of ``apply`` scales with the cores
    (``bench/bench_apply.py``).
    """
    by_rows_many([(fn, arrays)], workers)


def by_rows_many(tasks: list[tuple[Callable, tuple[np.ndarray, ...]]], workers: int) -> None:
    """:func:`by_rows` for several ``(fn, arrays)`` at once: each thread runs every
    task on its own block of rows (each task's arrays split by their own row count), so
    that consecutive element-wise steps cost one hand-over between threads, not one
    each."""
    n = min(a[0].shape[0] for _, a in tasks)
    if workers <= 1 or n < 256:
        for fn, arrays in tasks:
            fn(*arrays)
        return
    pool = _pool(workers)

    def run(k: int) -> None:
        for fn, arrays in tasks:
            m = arrays[0].shape[0]
            lo, hi = m * k // workers, m * (k + 1) // workers
            fn(*(a[lo:hi] for a in arrays))

    futures = [pool.submit(run, k) for k in range(1, workers)]
    run(0)
    for f in futures:
        f.result()


def map_rows(fn: Callable[[slice], object], n_rows: int, workers: int, *,
             chunk: int = 32) -> list:
    """``[fn(rows) for rows in chunks]`` over slices of ``chunk`` rows covering
    ``range(n_rows)``, run on ``workers`` threads, each taking a contiguous run of chunks.

    For fused element-wise work: ``fn`` indexes every array it needs with ``rows``, and
    several operations on one chunk reuse it from the cache (a chunk of 32 rows of a
    2048-wide float32 image is 256 kB). Returns the results in row order.
    """
    chunks = [slice(lo, min(lo + chunk, n_rows)) for lo in range(0, n_rows, chunk)]
    if workers <= 1 or len(chunks) < 2 * workers:
        return [fn(rows) for rows in chunks]
    pool = _pool(workers)
    edges = np.linspace(0, len(chunks), workers + 1).astype(int)

    def run(lo: int, hi: int) -> list:
        return [fn(rows) for rows in chunks[lo:hi]]

    futures = [pool.submit(run, lo, hi) for lo, hi in zip(edges[1:-1], edges[2:],
                                                            strict=True)]
    out = run(edges[0], edges[1])
    for f in futures:
        out.extend(f.result())
    return out


def filter_by_rows(fn: Callable[[np.ndarray], np.ndarray], image: np.ndarray, halo: int,
                   workers: int | None = None) -> np.ndarray:
    """``fn(image)`` for a neighbourhood filter reaching ``halo`` rows, on row blocks in
    parallel threads; the same result as one call (each block is filtered with ``halo``
    rows of its neighbours, the image's own edges keep the filter's boundary mode).

    The result is bit-identical to one call (tested); ``bench/bench_speed.py`` times
    the estimate that filters this way.
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
