from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


@pytest.fixture(scope="session")
def bodytrack_dir() -> Path:
    d = SHARED_DATA / "multiview" / "bodytrack_sequenceB_1"
    if not (d / "CALIB" / "Camera1.cal").exists():
        pytest.skip(f"shared data not found at {d}")
    return d
