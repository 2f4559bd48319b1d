from pathlib import Path

import numpy as np
import pytest

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
BODYTRACK = SHARED_DATA / "multiview" / "bodytrack_sequenceB_1"


@pytest.fixture(scope="session")
def bodytrack_dir() -> Path:
    if not (BODYTRACK / "CALIB" / "Camera1.cal").exists():
        pytest.skip(f"shared data not found at {BODYTRACK}")
    return BODYTRACK


@pytest.fixture(scope="session")
def bodytrack_calibs(bodytrack_dir) -> list[Path]:
    return [bodytrack_dir / "CALIB" / f"Camera{i}.cal" for i in range(1, 5)]


@pytest.fixture(scope="session")
def bodytrack_masks(bodytrack_dir) -> np.ndarray:
    from PIL import Image

    return np.stack([np.array(Image.open(bodytrack_dir / f"FG{i}" / "image0000.bmp"))
                     for i in range(1, 5)])
