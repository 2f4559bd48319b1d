from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def bodytrack_dir(shared_data) -> Path:
    """The bodytrack frame vendored in tests/data_files."""
    return shared_data / "multiview" / "bodytrack_sequenceB_1"
