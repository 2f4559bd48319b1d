"""Shared fixtures of the io tests: the real mocap files (trimmed copies in tests/data_files)."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def cmu(shared_data: Path) -> Path:
    return shared_data / "mocap" / "cmu"


@pytest.fixture(scope="session")
def hdm05(shared_data: Path) -> Path:
    return shared_data / "mocap" / "hdm05"
