from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


@pytest.fixture(scope="session")
def makehuman_dir() -> Path:
    d = SHARED_DATA / "body" / "makehuman_cc0"
    if not (d / "base.obj").exists():
        pytest.skip(f"shared data not found at {d}")
    return d
