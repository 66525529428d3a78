"""CoreTask: Cancel is honoured while the core is in a long step that cannot yield (every
phase of every step), and the core is closed after that step."""

from __future__ import annotations

import threading

from magicgui.widgets import PushButton

from napari_psfspace._widgets._worker import CoreTask
from napari_psfspace.core.common.progress import Progress


def test_cancel_while_the_core_is_blocked(qtbot):
    release, closed, after, results = (threading.Event(), threading.Event(), [], [])

    def core():
        try:
            yield Progress("one", 0.3, "first")
            release.wait(60)  # a long step: no record until it ends
            after.append("the step under way ended")
            yield Progress("two", 0.6, "second")
            after.append("a step after Cancel ran")
            return "value"
        finally:
            closed.set()

    start = PushButton(text="go")
    task = CoreTask(start)
    guard = threading.Timer(30, release.set)  # a broken door fails below, never hangs
    guard.start()
    task.run(core(), results.append)
    qtbot.waitUntil(lambda: task.status.value == "first", timeout=10_000)
    task.cancel.clicked()
    # the job ends, and the panel is free again, while the core's step still runs
    qtbot.waitUntil(lambda: not task.running, timeout=10_000)
    assert not release.is_set(), "Cancel waited for the core's step to end"
    assert task.status.value.startswith("cancelled") and start.enabled
    release.set()
    guard.cancel()
    assert closed.wait(30)  # closed after its step ...
    assert after == ["the step under way ended"]  # ... and nothing after it ran
    assert results == []  # no result handler after a Cancel


def test_a_cancel_after_the_last_step_drops_the_result(qtbot):
    """Cancel clicked after the core's last step, before its result reached the panel
    (a busy machine): the result is dropped and the panel says cancelled, as for a Cancel
    in any other step (not 'cancelling...' for ever, with the result applied)."""
    returning, results, cancels = threading.Event(), [], []

    def core():
        yield Progress("one", 0.5, "first")
        returning.set()
        return "value"

    start = PushButton(text="go")
    task = CoreTask(start)
    task.run(core(), results.append, on_cancel=lambda: cancels.append(True))
    # the core has returned in its thread; the panel has not yet run its result handler
    # (that waits for this thread's event loop, which runs only in waitUntil below)
    assert returning.wait(30)
    task.request_cancel()
    qtbot.waitUntil(lambda: not task.running, timeout=30_000)
    assert results == [] and cancels == [True]
    assert task.status.value.startswith("cancelled") and start.enabled
