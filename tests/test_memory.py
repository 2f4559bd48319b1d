"""torchmocap.memory: a request above the available memory is refused naming the setting."""

from __future__ import annotations

import pytest

from torchmocap.memory import MemoryBudgetError, available_memory, check_memory, format_bytes


def test_feature_available_memory_is_positive():
    free = available_memory()
    assert isinstance(free, int) and free > 0


def test_exception_request_above_available(monkeypatch):
    import torchmocap.memory as m

    monkeypatch.setattr(m, "available_memory", lambda device=None: 2_000_000_000)
    check_memory(1.9e9, "particles", "num_particles")  # fits: nothing happens
    with pytest.raises(MemoryBudgetError,
                       match=r"^num_particles: particles need at least 64 GB, but 2 GB are "):
        check_memory(64e9, "particles", "num_particles")


def test_feature_format_bytes():
    assert format_bytes(64e9) == "64 GB" and format_bytes(1.47e12) == "1.47 TB"
    assert format_bytes(512) == "512 B" and format_bytes(2.5e6) == "2.5 MB"
