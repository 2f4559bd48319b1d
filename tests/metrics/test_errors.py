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


def test_root_aligned_mpjpe():
    """``root=`` removes a global offset (a monocular camera's depth of the whole body) and
    keeps the error of the pose itself: closed forms, and the global MPJPE is unchanged."""
    g = torch.Generator().manual_seed(1)
    tru = torch.randn(4, 5, 3, generator=g, dtype=torch.float64)
    shift = torch.randn(4, 1, 3, generator=g, dtype=torch.float64)
    assert mpjpe_mm(tru + shift, tru, root=0).abs().max() < 1e-9
    assert torch.allclose(mpjpe_mm(tru + shift, tru), shift.norm(dim=-1)[:, 0] * 1000)
    # one joint (not the root) off by 2 cm: the root-aligned error is 2 cm / 5 joints
    est = tru + shift
    est[:, 3] += torch.tensor([0.0, 0.02, 0.0], dtype=torch.float64)
    assert mpjpe_mm(est, tru, root=0).tolist() == pytest.approx([4.0] * 4)
    # the root itself off by 2 cm: every other joint is then 2 cm off after alignment
    est = tru.clone()
    est[:, 0] += torch.tensor([0.02, 0.0, 0.0], dtype=torch.float64)
    assert mpjpe_mm(est, tru, root=0).tolist() == pytest.approx([16.0] * 4)
    assert mpjpe_mm(est, tru, root=-5).tolist() == pytest.approx([16.0] * 4)
    s = summarize_errors(torch.ones(4, 1), ["a"], mpjpe_mm(est, tru), mpjpe_mm(est, tru, root=0))
    assert s["mpjpe_root_relative_mm"]["mean"] == pytest.approx(16.0)
    assert "mpjpe_root_relative_mm" not in summarize_errors(torch.ones(4, 1), ["a"],
                                                            mpjpe_mm(est, tru))
    for bad in (5, -6, 1.0, True, "pelvis"):
        with pytest.raises(ValueError, match="root"):
            mpjpe_mm(est, tru, root=bad)
