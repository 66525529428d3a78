"""The C heap kept between a long computation's large temporaries.

A 3D deblur allocates and frees arrays of tens of MB many times a second (each block's
padded volume, spectra and products). glibc's ``malloc`` hands a freed block above its
mmap threshold (128 KB, rising with use up to 32 MB) back to the system, and trims the
heap's free top above its trim threshold; every new array then faults its pages in again,
each zeroed by the kernel. On a 2-core machine that zeroing took about a third of a tiled
deblur's CPU time (``perf``), and two processes doing it at once scale worse than their
FFTs do.

:func:`kept_heap` raises both thresholds for the length of a run, so freed blocks below
32 MB (glibc's largest threshold on 64-bit) are reused from the heap; on leaving it
returns the free memory to the system (``malloc_trim``) and sets the trim threshold to
twice the mmap threshold, where glibc's own rule puts it once large blocks have been
freed (the mmap threshold stays at 32 MB, where that rule lets it rise). Where a
run's tasks execute in a worker process of their own (a dask cluster's),
:func:`keep_heap_in_worker` sets the thresholds once for that process's life. Elsewhere
than glibc both do nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import sys
import threading
from collections.abc import Iterator

#: ``mallopt`` parameters (glibc's ``malloc.h``).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: The mmap threshold during a run: glibc's largest on 64-bit (``4 * 1024 * 1024 *
#: sizeof(long)``); blocks above it are mapped whatever is asked.
KEPT_MMAP_THRESHOLD = 32 * 1024 * 1024
#: The trim threshold during a run: the largest ``mallopt`` takes (a C int); the free top
#: of the heap is kept up to it.
KEPT_TRIM_THRESHOLD = 2**31 - 1
#: The trim threshold after a run: twice the mmap threshold, as glibc's own rule sets it.
AFTER_TRIM_THRESHOLD = 2 * KEPT_MMAP_THRESHOLD

_lock = threading.Lock()
_depth = 0
_worker_kept = False


def _glibc():
    """glibc's handle, or None where the C library is another (macOS, Windows, musl)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        if not hasattr(libc, "gnu_get_libc_version"):  # glibc only
            return None
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
    except OSError:
        return None
    return libc


def _keep(libc) -> None:
    libc.mallopt(M_MMAP_THRESHOLD, KEPT_MMAP_THRESHOLD)
    libc.mallopt(M_TRIM_THRESHOLD, KEPT_TRIM_THRESHOLD)


@contextlib.contextmanager
def kept_heap() -> Iterator[None]:
    """A context in which freed blocks under 32 MB stay in the process's heap for the next
    allocation (module docstring); nested and concurrent uses share one setting. When the
    last leaves, the heap's free memory goes back to the system and the trim threshold
    to glibc's steady value."""
    global _depth
    libc = _glibc()
    if libc is None:
        yield
        return
    with _lock:
        if _depth == 0 and not _worker_kept:
            _keep(libc)
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and not _worker_kept:
                libc.mallopt(M_TRIM_THRESHOLD, AFTER_TRIM_THRESHOLD)
                libc.malloc_trim(0)


def keep_heap_in_worker() -> None:
    """Keep the heap for the rest of this process's life, where it is a dask cluster's
    worker process (its tasks are the run's; nothing else lives there); elsewhere, as in
    a cluster whose workers are threads of the caller's process, nothing."""
    global _worker_kept
    if _worker_kept:
        return
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return
    import multiprocessing

    if worker is None or multiprocessing.parent_process() is None:
        return  # the caller's own process
    libc = _glibc()
    with _lock:
        if libc is not None and not _worker_kept:
            _keep(libc)
            _worker_kept = True


__all__ = ["kept_heap", "keep_heap_in_worker"]
