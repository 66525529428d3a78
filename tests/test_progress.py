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
