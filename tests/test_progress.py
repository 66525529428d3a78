"""A long step that cannot yield itself keeps its generator answering (Cancel)."""

import threading
import time

import pytest

from napari_psfspace.core.common.progress import (
    Halted,
    Progress,
    check_halt,
    responsive,
    run_with_progress,
    wait_with_progress,
)

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


def _blocked_step(release: threading.Event, done: threading.Event):
    """A step that runs until ``release`` is set, then sets ``done``."""
    def step():
        release.wait(30)
        done.set()
    return step


def test_a_consumer_that_stops_is_answered_before_the_step_ends():
    release, done = threading.Event(), threading.Event()
    gen = wait_with_progress(_blocked_step(release, done), RECORD, every=0.05)
    assert next(gen) == RECORD
    gen.close()  # Cancel between two records
    assert not done.is_set()  # answered while the step still runs (a signal, no clock)
    release.set()  # the step ends on its own
    assert done.wait(30)


def test_a_family_compute_in_its_own_thread_uses_no_more_threads_than_cores():
    """dask's threads scheduler, called from a thread other than the main one, would make
    a pool of Python's default size (cores + 4): on 2 cores that oversubscribed them and
    made learning a family half as slow again. The family's computes name their workers."""
    import dask
    from dask.system import CPU_COUNT

    from napari_psfspace.core.common.threads import compute_tasks as _compute

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
    release, done = threading.Event(), threading.Event()
    left = wait_with_progress(_blocked_step(release, done), RECORD, every=0.05)
    next(left)
    left.close()  # Cancel: the step runs on
    other = run_with_progress(wait_with_progress(threading.get_ident, RECORD, every=0.05))
    # the other step ran while the one left running still waits (queued behind it, it
    # would have run only once that one ended)
    assert not done.is_set() and other != threading.get_ident()
    release.set()
    assert done.wait(30)


# ------------------------------------------------------------------ responsive (the panel's door)
def _core(release: threading.Event, after: list, closed: threading.Event):
    """A core generator with a long step that cannot yield (blocked on ``release``)."""
    try:
        yield Progress("one", 0.25, "first")
        release.wait(60)
        after.append("the step after the long one ran")
        yield Progress("two", 0.5, "second")
        return "value"
    finally:
        closed.set()


def test_responsive_passes_the_records_and_the_value_on():
    release, closed, after = threading.Event(), threading.Event(), []
    release.set()
    seen = []
    value = run_with_progress(responsive(_core(release, after, closed), every=0.05),
                              seen.append)
    assert value == "value" and closed.is_set()
    own = [r for r in seen if r.stage in ("one", "two")]
    assert [r.message for r in own] == ["first", "second"]
    # anything else is a repeat of the latest record (or the starting one)
    assert all(r.stage in ("one", "two", "start") for r in seen)


def test_responsive_answers_while_the_core_is_blocked_and_closes_it_after_its_step():
    release, closed, after = threading.Event(), threading.Event(), []
    gen = responsive(_core(release, after, closed), every=0.01)
    guard = threading.Timer(30, release.set)  # a broken door fails below, never hangs
    guard.start()
    records = [next(gen) for _ in range(5)]  # the core is blocked after its first record
    assert not release.is_set()
    assert records[-1].message == "first"  # the latest record, repeated
    gen.close()  # Cancel, while the core's step still runs
    assert not closed.is_set()
    release.set()  # the step ends on its own: then the core is closed
    assert closed.wait(30)
    guard.cancel()
    assert after == ["the step after the long one ran"]  # the step under way ended
    # ... and nothing after it: the second record was never asked for


def test_responsive_raises_the_core_error():
    def core():
        yield RECORD
        raise ValueError("`psf_radius`: bad")

    with pytest.raises(ValueError, match="`psf_radius`: bad"):
        run_with_progress(responsive(core(), every=0.01))


def _checking(started, stopped, pieces, n=100_000):
    """A long part with no record, checking for a halt between its pieces (1 ms each:
    about 100 s in all); ``stopped`` is set however it ends."""
    try:
        for k in range(n):
            started.set()
            pieces.append(k)
            check_halt()
            time.sleep(0.001)
    finally:
        stopped.set()
    return "ran to its end"


@pytest.mark.parametrize("where", ["in the generator", "in a step's thread"])
def test_a_cancelled_computation_stops_at_its_next_check_not_at_its_next_record(where):
    """After Cancel the work itself stops, not only the panel's wait: a long part that
    checks (``check_halt``) between its pieces ends within a piece, in the generator's
    own thread and in the thread of a step it waits on (``wait_with_progress``)."""
    started, stopped, pieces = threading.Event(), threading.Event(), []

    def core():
        yield RECORD
        if where == "in the generator":
            _checking(started, stopped, pieces)
        else:
            yield from wait_with_progress(lambda: _checking(started, stopped, pieces), RECORD,
                                          every=0.01)
        yield Progress("never", 1.0)

    gen = responsive(core(), every=0.01)
    for _ in range(3000):  # the panel asks for records (each within 0.01 s) ...
        next(gen)
        if started.is_set():  # ... until the long part is under way
            break
    assert started.is_set()
    gen.close()  # Cancel
    # it stops at its next check: long before the 100 000 pieces (about 100 s) are done
    assert stopped.wait(30)
    assert len(pieces) < 100_000


def test_check_halt_does_nothing_outside_a_cancelled_computation():
    """Run by a script (no panel), or before a Cancel, the checks never stop the work."""
    started, stopped, pieces = threading.Event(), threading.Event(), []
    assert _checking(started, stopped, pieces, n=50) == "ran to its end"
    assert len(pieces) == 50

    def core():
        yield RECORD
        return _checking(started, stopped, pieces, n=50)

    assert run_with_progress(responsive(core(), every=0.01)) == "ran to its end"
    assert issubclass(Halted, BaseException) and not issubclass(Halted, Exception)
