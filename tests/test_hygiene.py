"""The test-suite conventions of tests/conftest.py hold (seeded global RNGs, one thread, a
derandomized hypothesis profile for CI, vendored data)."""

from __future__ import annotations

import random
import zlib

import numpy as np
import torch


def test_global_rng_is_seeded_per_test(request):
    seed = zlib.crc32(request.node.nodeid.encode())
    expect = torch.rand(3, generator=torch.Generator().manual_seed(seed))
    assert torch.equal(torch.rand(3), expect)
    assert np.random.rand() == np.random.RandomState(seed).rand()
    assert random.random() == random.Random(seed).random()


def test_one_torch_thread():
    assert torch.get_num_threads() == 1


def test_hypothesis_ci_profile():
    from hypothesis import settings

    ci = settings.get_profile("ci")
    assert ci.derandomize and ci.deadline is None


def test_vendored_data_is_used(shared_data):
    from pathlib import Path

    assert shared_data == Path(__file__).resolve().parent / "data_files"
    assert (shared_data / "README.md").is_file()
    total = sum(p.stat().st_size for p in shared_data.rglob("*") if p.is_file())
    assert total < 6e6  # a few MB at most (4.6 MB with the pose2sim frames)
