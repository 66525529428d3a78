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
