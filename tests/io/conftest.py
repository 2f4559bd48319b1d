"""Shared fixtures of the io tests: the real mocap folder beside the checkout."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).parents[2] / ".." / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (skips the test with a message when the folder is missing)."""
    if not (SHARED_DATA / "mocap").is_dir():
        pytest.skip(f"shared data folder not found at {SHARED_DATA.resolve()}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def cmu(shared_data: Path) -> Path:
    return shared_data / "mocap" / "cmu"


@pytest.fixture(scope="session")
def hdm05(shared_data: Path) -> Path:
    return shared_data / "mocap" / "hdm05"
