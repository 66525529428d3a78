"""A long step that cannot yield itself keeps its generator answering (Cancel)."""

import threading
import time

import pytest

from napari_psfspace.core.common.progress import Progress, run_with_progress, wait_with_progress

RECORD = Progress("step", 0.5, "running")


def test_the_step_value_comes_back_and_the_record_repeats_while_it_runs():
    seen = []
    value = run_with_progress(wait_with_progress(lambda: time.sleep(0.35) or 42, RECORD,
                                                 every=0.05), seen.append)
    assert value == 42
    assert len(seen) >= 2 and set(seen) == {RECORD}


def test_a_quick_step_yields_nothing():
    seen = []
    assert run_with_progress(wait_with_progress(lambda: "done", RECORD), seen.append) == "done"
    assert seen == []


def test_the_step_error_reaches_the_consumer():
    def fail():
        raise ValueError("`images`: bad")

    with pytest.raises(ValueError, match="`images`: bad"):
        run_with_progress(wait_with_progress(fail, RECORD, every=0.01))


def test_a_consumer_that_stops_is_answered_before_the_step_ends():
    release = threading.Event()
    gen = wait_with_progress(lambda: release.wait(30), RECORD, every=0.05)
    t0 = time.perf_counter()
    assert next(gen) == RECORD
    gen.close()  # Cancel between two records
    stopped = time.perf_counter() - t0
    release.set()  # the step ends on its own
    assert stopped < 5.0  # the step alone would have taken 30 s


def test_a_family_compute_in_its_own_thread_uses_no_more_threads_than_cores():
    """dask's threads scheduler, called from a thread other than the main one, would make
    a pool of Python's default size (cores + 4): on 2 cores that oversubscribed them and
    made learning a family half as slow again. The family's computes name their workers."""
    import dask
    from dask.system import CPU_COUNT

    from napari_psfspace.core.subspace.estimate import _compute

    def who(_):
        time.sleep(0.02)  # long enough for every worker of the pool to take a task
        return threading.get_ident()

    tasks = [dask.delayed(who)(i) for i in range(8 * (CPU_COUNT + 4))]
    idents = run_with_progress(wait_with_progress(lambda: _compute(tasks, None), RECORD,
                                                  every=0.05))
    assert len(set(idents)) <= CPU_COUNT
    # a user's dask setting is kept
    with dask.config.set(num_workers=1):
        idents = run_with_progress(wait_with_progress(lambda: _compute(tasks, None), RECORD,
                                                      every=0.05))
    assert len(set(idents)) == 1


def test_steps_reuse_their_thread_and_one_left_running_holds_up_no_other():
    first = run_with_progress(wait_with_progress(threading.get_ident, RECORD))
    assert run_with_progress(wait_with_progress(threading.get_ident, RECORD)) == first
    release = threading.Event()
    left = wait_with_progress(lambda: release.wait(30), RECORD, every=0.05)
    next(left)
    left.close()  # Cancel: the step runs on
    t0 = time.perf_counter()
    other = run_with_progress(wait_with_progress(threading.get_ident, RECORD, every=0.05))
    assert time.perf_counter() - t0 < 5.0 and other != threading.get_ident()
    release.set()
