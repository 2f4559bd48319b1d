"""Shared fixtures: dtype/device selection, tolerances, test data, and test hygiene.

Test data: trimmed copies of the real recordings (``tests/data_files``, see its README) ship with
the repository, so a fresh clone runs every test; none is skipped for missing data, and in CI
(the ``CI`` environment variable set) a missing file fails the test loudly.

Hygiene (autouse): every test starts from seeded global RNGs (torch, numpy, random) and with one
torch thread, so a test that forgets its ``torch.Generator`` is still reproducible and timings
do not depend on the machine's core count. Hypothesis runs derandomized in CI.
"""

from __future__ import annotations

import os
import random
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

#: trimmed real recordings vendored with the tests (layout of ``../shared/data``)
DATA_FILES = Path(__file__).resolve().parent / "data_files"
#: kept for code that still refers to it: the vendored copies stand in for ``../shared/data``
SHARED_DATA = DATA_FILES

try:  # a derandomized profile for CI: the same examples on every run
    from hypothesis import settings as _hyp_settings

    _hyp_settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
    if os.environ.get("CI"):
        _hyp_settings.load_profile("ci")
except ImportError:  # pragma: no cover - hypothesis is a dev dependency
    pass


def pytest_addoption(parser):
    parser.addoption("--device", default="cpu", help="device for tests: cpu or cuda")


@pytest.fixture(autouse=True)
def _seeded_global_rng(request):
    """Seed torch, numpy and ``random`` per test (from the test's id: stable, distinct per
    test) and pin ``torch.set_num_threads(1)``; restore the thread count afterwards."""
    seed = zlib.crc32(request.node.nodeid.encode())
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def require_data(path: Path) -> Path:
    """``path`` under :data:`DATA_FILES`, which must exist: a missing file fails the test in CI
    and skips it (with the reason) elsewhere, e.g. in a partial checkout."""
    if not path.exists():
        msg = (f"test data missing: {path} (tests/data_files ships with the repository; "
               "rebuild it with tests/data_files/make_data_files.py)")
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return path


@pytest.fixture
def device(request) -> torch.device:
    dev = request.config.getoption("--device")
    if dev.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip("CUDA requested but not available")
    return torch.device(dev)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param


def tol(dtype: torch.dtype) -> float:
    """Absolute tolerance for closed-form comparisons at this precision."""
    return 1e-5 if dtype == torch.float32 else 1e-10


@pytest.fixture(scope="session")
def data_file():
    """:func:`require_data` for conftests and tests: ``data_file("body/x.xz") -> Path``."""
    return lambda rel: require_data(DATA_FILES / rel)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real-recordings folder: the trimmed copies in ``tests/data_files`` (same layout as
    ``../shared/data``: ``mocap/``, ``multiview/``, ``body/``)."""
    require_data(DATA_FILES / "mocap")
    require_data(DATA_FILES / "multiview" / "bodytrack_sequenceB_1" / "CALIB")
    return DATA_FILES


#: the trimmed pose2sim_balancing recording's cameras and its frames of associated detections
POSE2SIM_CAMERAS = ("cam01", "cam02", "cam03", "cam04")
POSE2SIM_FRAMES = 10


@pytest.fixture(scope="session")
def pose2sim_root(shared_data) -> Path:
    """The trimmed real 4-camera recording (``tests/data_files/multiview/pose2sim_balancing``)."""
    return require_data(shared_data / "multiview" / "pose2sim_balancing")


@pytest.fixture(scope="session")
def pose2sim_calibrated_rig(pose2sim_root):
    """Its calibration (``Calib.toml``, read by the project's reader; float64, the calibrated
    1088x1920 image size of every camera)."""
    from torchmocap.cameras import read_toml_calibration

    return read_toml_calibration(pose2sim_root / "calibration" / "Calib.toml").double()


@pytest.fixture(scope="session")
def pose2sim_detections(pose2sim_root) -> torch.Tensor:
    """The subject's BODY_25B detections ``(T=10, C=4, 25, 3)`` (u, v, confidence; full
    resolution pixels) from the associated OpenPose files, float64."""
    from torchmocap.io.openpose import read_openpose_json

    rows = []
    for t in range(POSE2SIM_FRAMES):
        rows.append(torch.stack([
            read_openpose_json(pose2sim_root / "pose-associated" / f"{cam}_json" /
                               f"{cam}.{t:04d}.json", 25)[0] for cam in POSE2SIM_CAMERAS]))
    return torch.stack(rows).double()
