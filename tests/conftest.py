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

    if _EXIT_STATUS and any(m in sys.modules for m in ("PyQt6", "PyQt5", "PySide6")):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[-1])
