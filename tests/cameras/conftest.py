from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="session")
def bodytrack_dir(shared_data) -> Path:
    """The bodytrack frame (calibrations, masks, grey images) vendored in tests/data_files."""
    return shared_data / "multiview" / "bodytrack_sequenceB_1"


@pytest.fixture(scope="session")
def bodytrack_calibs(bodytrack_dir) -> list[Path]:
    return [bodytrack_dir / "CALIB" / f"Camera{i}.cal" for i in range(1, 5)]


@pytest.fixture(scope="session")
def bodytrack_masks(bodytrack_dir) -> np.ndarray:
    """``(4, 480, 640)`` uint8 foreground masks (0/255)."""
    from PIL import Image

    return np.stack([np.array(Image.open(bodytrack_dir / f"FG{i}" / "image0000.png"))
                     for i in range(1, 5)])
