"""The C heap kept between a run's large temporaries (core.common.heap)."""

import resource

import numpy as np
import pytest

from napari_psfspace.core.common import heap

glibc = pytest.mark.skipif(heap._glibc() is None, reason="the C library is not glibc: "
                           "the heap's thresholds are glibc's (mallopt)")

#: An array under the kept mmap threshold (32 MB) and far over glibc's default (128 KB).
SIZE = 16 * 2**20 // 8


def _faults_of_a_second_array() -> int:
    """Page faults of writing a fresh array of SIZE float64 after one as large was freed:
    none where the heap kept the first's pages, one a page (4 KB, or 2 MB where the
    array is on huge pages) where they went back to the system."""
    a = np.ones(SIZE)
    del a
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    b = np.ones(SIZE)
    after = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    del b
    return after - before


def _resident() -> int:
    """The process's resident bytes."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


@glibc
def test_a_freed_array_is_reused_inside_and_the_memory_given_back_after():
    """Inside ``kept_heap`` a freed 16 MB array's pages serve the next one (no fault of
    its own: a few from the interpreter at most), and 12 such arrays freed stay resident
    (192 MB); on leaving, the heap's free memory goes back to the system: at least 150 MB
    of them (the rest may be held by other allocations above them)."""
    with heap.kept_heap():
        with heap.kept_heap():  # nested: one setting
            pass
        inside = _faults_of_a_second_array()
        arrays = [np.ones(SIZE) for _ in range(12)]
        del arrays
        held = _resident()
    given_back = held - _resident()
    assert inside <= 4, inside
    assert given_back >= 150 * 2**20, given_back / 2**20


def test_outside_a_cluster_worker_the_process_is_left_as_it_is():
    """``keep_heap_in_worker`` in the caller's own process (not a cluster's worker)
    changes nothing."""
    heap.keep_heap_in_worker()
    assert heap._worker_kept is False
