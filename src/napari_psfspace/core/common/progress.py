"""Progress of long computations: one record type and one way to run a generator.

Every long computation of the core is a generator ``iter_NAME(...)`` that yields
:class:`Progress` records and returns its result; its twin ``NAME(..., progress=None)``
drains it with :func:`run_with_progress`. A GUI runs the generator in a worker thread
and stops between two records (Cancel); a script calls the function.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Generator
from concurrent.futures import Future, wait
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Progress:
    """One step of a long computation.

    Attributes
    ----------
    stage : str
        Short name of the step that just finished.
    fraction : float
        Fraction of the whole computation done, in [0, 1].
    message : str
        Human-readable detail.
    """

    stage: str
    fraction: float
    message: str = ""


ProgressCallback = Callable[[Progress], None]


class Halted(BaseException):
    """Raised by :func:`check_halt` in a computation whose consumer has stopped (a panel's
    Cancel): the computation's thread stops at its next check instead of working on to its
    next record. A ``BaseException``, as ``GeneratorExit`` is, so that no ``except
    Exception`` of the computation takes it for a failure of its own."""


#: The halt event of the computation each thread works for (:func:`responsive` sets it
#: in its driver thread; :func:`wait_with_progress` hands it to the thread of its step).
_LOCAL = threading.local()


def check_halt() -> None:
    """Raise :class:`Halted` when the computation this thread works for was cancelled;
    else nothing (one attribute read and an event test: cheap in any loop).

    Long parts of a computation that yield no record call it between their pieces, so
    that after a Cancel the work stops within one piece, not at the next record."""
    halt = getattr(_LOCAL, "halt", None)
    if halt is not None and halt.is_set():
        raise Halted


def _halting(fn: Callable[[], Any], halt: threading.Event | None) -> Callable[[], Any]:
    """``fn`` run with ``halt`` as its thread's halt event (:func:`check_halt`)."""

    def run():
        before = getattr(_LOCAL, "halt", None)
        _LOCAL.halt = halt
        try:
            return fn()
        finally:
            _LOCAL.halt = before

    return run


def within(gen: Generator[Progress, None, Any], start: float, span: float
           ) -> Generator[Progress, None, Any]:
    """The records of a nested computation, its fractions placed within ``start ..
    start + span`` of the caller's; returns its value (``yield from within(...)``)."""
    while True:
        try:
            rec = next(gen)
        except StopIteration as stop:
            return stop.value
        yield Progress(rec.stage, start + span * float(rec.fraction), rec.message)


def run_with_progress(gen: Generator[Progress, None, Any],
                      progress: ProgressCallback | None = None) -> Any:
    """Drain a progress generator, calling ``progress`` on each record; return its value.

    Parameters
    ----------
    gen : generator
        Yields :class:`Progress` records, returns the result.
    progress : callable, optional
        Called with each record.

    Returns
    -------
    object
        The generator's return value.
    """
    while True:
        try:
            rec = next(gen)
        except StopIteration as stop:
            return stop.value
        if progress is not None:
            progress(rec)


def wait_with_progress(fn: Callable[[], Any], record: Progress, *,
                       every: float = 0.2) -> Generator[Progress, None, Any]:
    """Run ``fn()`` in another thread, yielding ``record`` every ``every`` seconds
    until it returns; return its value (or raise its exception).

    A long step that cannot yield itself (one ``dask.compute`` of many tasks) then keeps
    its generator answering: a consumer that stops between two records (Cancel) is
    answered within ``every`` seconds. The step itself runs on to its end in its thread
    (a compute cannot be interrupted), and its result is dropped.

    Parameters
    ----------
    fn : callable
        The step, without arguments.
    record : Progress
        Yielded while it runs.
    every : float
        Seconds between two records.
    """
    future = _steps().submit(_halting(fn, getattr(_LOCAL, "halt", None)))
    while True:
        done, _ = wait([future], timeout=float(every))
        if done:
            return future.result()  # its value, or its exception raised here
        yield record


def responsive(gen: Generator[Progress, None, Any], *, every: float = 0.2
               ) -> Generator[Progress, None, Any]:
    """Drive ``gen`` from a helper thread and pass its records on, repeating the latest
    one every ``every`` seconds while ``gen`` works between two of its own.

    A consumer that stops between two records (a panel's Cancel) is then answered within
    ``every`` seconds in every phase, however long ``gen``'s own steps are. The step
    ``gen`` is in runs on in its thread to its next record or to its next
    :func:`check_halt`, whichever comes first; then ``gen`` is closed, and nothing after
    that runs. Returns ``gen``'s value (or raises its exception).

    Parameters
    ----------
    gen : generator
        A core generator (not started) yielding :class:`Progress` records.
    every : float
        The longest time between two records, in seconds.
    """
    last = Progress("start", 0.0, "starting...")
    done = object()
    halt = threading.Event()

    def step():
        try:
            return next(gen)
        except StopIteration as stop:
            return done, stop.value

    def close(_future=None) -> None:
        try:
            gen.close()  # its own clean-up (a halt event, a file) runs now
        except (RuntimeError, ValueError):  # pragma: no cover (already executing)
            pass

    future = None
    try:
        while True:
            future = _drivers().submit(_halting(step, halt))
            while True:
                finished, _ = wait([future], timeout=float(every))
                if finished:
                    break
                yield last
            got = future.result()  # gen's exception is raised here
            if isinstance(got, tuple) and len(got) == 2 and got[0] is done:
                return got[1]
            last = got
            yield got
    except GeneratorExit:  # the consumer stopped: gen is closed after its step
        halt.set()  # which stops at its next check_halt()
        if future is not None:
            future.add_done_callback(close)
        raise


#: Threads for :func:`wait_with_progress`: reused from one step to the next (dask keeps a
#: pool of workers per calling thread, and each new thread also costs its own memory
#: arena); more than one, so that a step left running by a Cancel does not hold up the
#: next run's. Daemon threads: a step left running never holds up the interpreter's exit.
STEP_THREADS = 4


class _StepThreads:
    """A few daemon threads that run submitted calls, started as needed."""

    def __init__(self, n: int):
        self._n, self._queue = int(n), queue.SimpleQueue()
        self._lock, self._idle, self._threads = threading.Lock(), 0, 0

    def submit(self, fn: Callable[[], Any]) -> Future:
        future: Future = Future()
        with self._lock:
            if self._idle <= 0 and self._threads < self._n:
                self._threads += 1
                threading.Thread(target=self._work, daemon=True,
                                 name=f"psfspace-step-{self._threads}").start()
            self._idle -= 1  # this call takes one idle thread (or waits for one)
        self._queue.put((fn, future))
        return future

    def _work(self) -> None:
        while True:
            with self._lock:
                self._idle += 1
            fn, future = self._queue.get()
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the caller by future.result()
                future.set_exception(exc)


#: Threads that drive the generators of :func:`responsive` (apart from the steps' own
#: threads, which they wait on: a driver never waits for another driver).
DRIVER_THREADS = 8
_POOLS: dict[str, _StepThreads] = {}
_POOLS_LOCK = threading.Lock()


def _pool(kind: str, n: int) -> _StepThreads:
    """The process's pool of ``kind`` ("steps" or "drivers"), made on first use."""
    with _POOLS_LOCK:
        if kind not in _POOLS:
            _POOLS[kind] = _StepThreads(n)
        return _POOLS[kind]


def _drivers() -> _StepThreads:
    return _pool("drivers", DRIVER_THREADS)


def _steps() -> _StepThreads:
    return _pool("steps", STEP_THREADS)


__all__ = ["Halted", "Progress", "ProgressCallback", "check_halt", "responsive",
           "run_with_progress", "wait_with_progress", "within"]
