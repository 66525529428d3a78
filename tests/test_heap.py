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


@glibc
def test_a_freed_array_is_reused_inside_and_given_back_after():
    """Inside ``kept_heap`` a freed 16 MB array's pages serve the next one (no fault of
    its own: a few from the interpreter at most); after it the thresholds are glibc's
    defaults again and such an array is mapped afresh, every page faulted in (8 at
    least: 2 MB huge pages)."""
    with heap.kept_heap():
        with heap.kept_heap():  # nested: one setting
            pass
        inside = _faults_of_a_second_array()
    after = _faults_of_a_second_array()
    assert inside <= 4, inside
    assert after >= 8, after


def test_outside_a_cluster_worker_the_process_is_left_as_it_is():
    """``keep_heap_in_worker`` in the caller's own process (not a cluster's worker)
    changes nothing."""
    heap.keep_heap_in_worker()
    assert heap._worker_kept is False
