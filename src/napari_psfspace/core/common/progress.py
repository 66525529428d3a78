"""Progress of long computations: one record type and one way to run a generator.

Every long computation of the core is a generator ``iter_NAME(...)`` that yields
:class:`Progress` records and returns its result; its twin ``NAME(..., progress=None)``
drains it with :func:`run_with_progress`. A GUI runs the generator in a worker thread
and stops between two records (Cancel); a script calls the function.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Generator
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
    """Run ``fn()`` in a thread of its own, yielding ``record`` every ``every`` seconds
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
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:  # handed to the generator's consumer
            box["error"] = exc

    thread = threading.Thread(target=run, name="psfspace-step", daemon=True)
    thread.start()
    while True:
        thread.join(timeout=float(every))
        if not thread.is_alive():
            break
        yield record
    if "error" in box:
        raise box["error"]
    return box["value"]


__all__ = ["Progress", "ProgressCallback", "run_with_progress", "wait_with_progress"]
