"""Error metrics: eq. 19 against quaternion arithmetic (scipy), sensor offsets cancel, MPJPE."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from torchmocap.geometry import random_rotation_matrix
from torchmocap.metrics import mpjpe_mm, orientation_error_deg, summarize_errors


def test_orientation_error_is_eq19_in_degrees():
    g = torch.Generator().manual_seed(0)
    A = random_rotation_matrix((200,), generator=g, dtype=torch.float64)
    B = random_rotation_matrix((200,), generator=g, dtype=torch.float64)
    qa = Rotation.from_matrix(A.numpy()).as_quat()
    qb = Rotation.from_matrix(B.numpy()).as_quat()
    # eq. 19 (per pair): 2 arccos |<q1, q2>| in degrees, the printed form
    ref = 2 * torch.arccos(torch.from_numpy(abs((qa * qb).sum(-1))).clamp(max=1)) * 180 / math.pi
    assert torch.allclose(orientation_error_deg(A, B), ref, atol=1e-6)
    # a sensor-to-bone offset applied on the right of both cancels
    off = random_rotation_matrix((), generator=g, dtype=torch.float64)
    assert torch.allclose(orientation_error_deg(A @ off, B @ off), ref, atol=1e-6)
    with pytest.raises(ValueError, match="truth"):
        orientation_error_deg(A, B[:3])


def test_mpjpe_and_summary():
    est = torch.zeros(2, 3, 3)
    tru = torch.zeros(2, 3, 3)
    tru[0, :, 0] = 0.01  # 1 cm on every joint of frame 0
    tru[1, 0, 2] = 0.03  # 3 cm on one of three joints of frame 1
    assert mpjpe_mm(est, tru).tolist() == pytest.approx([10.0, 10.0])
    s = summarize_errors(torch.tensor([[1.0, 3.0], [3.0, 5.0]]), ["a", "b"],
                         mpjpe_mm(est, tru))
    assert s["orientation_error_deg"]["mean"] == 3.0
    assert s["orientation_error_deg"]["per_bone"] == {"a": 2.0, "b": 4.0}
    assert s["mpjpe_mm"]["mean"] == pytest.approx(10.0)
