import os
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The measured bead images of ../shared/data (skips where they are absent)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"measured data not found at {SHARED_DATA}: these tests need the "
                    "project's ../shared folder beside the repository (present in CI)")
    return SHARED_DATA


def _hypothesis_profiles() -> None:
    """The property-based tests' two profiles, for every test file: ``fast`` (the suite's:
    a few examples each, derandomised, so that every run is the same) and ``fuzz``
    (``make fuzz``: ``FUZZ_EXAMPLES`` each, 100 by default, random).
    ``HYPOTHESIS_PROFILE`` chooses."""
    try:
        from hypothesis import HealthCheck, settings
    except ImportError:  # the tests that need it skip
        return
    settings.register_profile("fast", max_examples=12, derandomize=True, deadline=None,
                              suppress_health_check=list(HealthCheck))
    settings.register_profile("fuzz", max_examples=int(os.environ.get("FUZZ_EXAMPLES", 100)),
                              deadline=None, suppress_health_check=list(HealthCheck))
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))


_hypothesis_profiles()


#: Tests that took a second or more (``tests/update_slow.py`` writes the list from a
#: run's durations): marked ``slow``, left out by ``make check``.
SLOW_LIST = Path(__file__).with_name("slow_tests.txt")


def _slow_tests() -> dict[str, float]:
    """The listed tests and their seconds."""
    if not SLOW_LIST.exists():
        return {}
    out = {}
    for line in SLOW_LIST.read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#"):
            seconds, test = line.split()
            out[test] = float(seconds)
    return out


#: Thread pools of the numerical libraries, one thread each in a parallel run.
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def pytest_configure(config):
    """Under pytest-xdist (``make test``: one worker per core), each worker's BLAS keeps one
    thread: OpenBLAS threads wait for work by spinning, so workers with a pool of one
    thread per core each spend much of the run's CPU time waiting on one another. The
    controller sets the variables before it starts the workers, which inherit them; a
    variable the caller set is kept."""
    workers = getattr(config.option, "numprocesses", None)
    if workers and not os.environ.get("PYTEST_XDIST_WORKER"):
        for name in _THREAD_VARIABLES:
            os.environ.setdefault(name, "1")


def pytest_collection_modifyitems(config, items):
    """Mark the tests of ``slow_tests.txt`` slow (by their id, or for a parametrised one
    listed without its parameters, all of them). Under pytest-xdist (``make test``, a file
    per worker at a time), the longest tests come first and with them their files, so
    that the workers end together (each worker sorts alike)."""
    slow = _slow_tests()
    seconds = {}
    for item in items:
        rel = item.nodeid if item.nodeid.startswith("tests/") else f"tests/{item.nodeid}"
        took = slow.get(rel, slow.get(rel.split("[")[0]))
        if took is not None:
            item.add_marker(pytest.mark.slow)
            seconds[item.nodeid] = took
    if os.environ.get("PYTEST_XDIST_WORKER"):
        items.sort(key=lambda item: -seconds.get(item.nodeid, 0.0))  # stable: ties keep order


# The napari widget tests leave Qt, vispy and napari objects whose destruction during the
# interpreter's own shutdown can crash it (a segmentation fault after "N passed": CI
# failed once so, every test having passed). Once the run is over and reported, a run
# that loaded Qt ends its process with pytest's exit status, skipping that finalisation.
_EXIT_STATUS: list[int] = []


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS.append(int(exitstatus))


def pytest_unconfigure(config):
    import os
    import sys

    if (_EXIT_STATUS and any(m in sys.modules for m in ("PyQt6", "PyQt5", "PySide6"))
            and not os.environ.get("PSFSPACE_TESTS_NO_HARD_EXIT")):  # e.g. under cProfile
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[-1])
