"""A user's own components, outside torchmocap: they enter trackers through YAML ``_target_``.

Used by tests/test_assembly.py (the package is put on ``sys.path`` / ``PYTHONPATH``).
"""

from __future__ import annotations

import torch

from torchmocap.data.recordings.keypoints.openpose import OpenPoseJson
from torchmocap.likelihoods import Likelihood
from torchmocap.proposals import GaussianDiffusionProposal


class UprightLikelihood(Likelihood):
    """Energy: how far the head is from straight above the pelvis (metres, horizontal).

    Takes the runtime ``skeleton`` by name (injected by ``torchmocap.assembly.build``)."""

    requires = ("silhouettes",)

    def __init__(self, skeleton, head: str = "head_top", scale: float = 1.0):
        super().__init__()
        self.head = skeleton.joint_index(head)
        self.scale = float(scale)
        self.calls = 0

    def energy(self, poses, observation):
        self.calls += 1
        p = poses.kinematics.positions
        return self.scale * (p[:, self.head, :2] - p[:, 0, :2]).norm(dim=-1)


class HalfStepProposal(GaussianDiffusionProposal):
    """A user's proposal: Gaussian diffusion at half the configured std."""

    def __init__(self, skeleton, rotation_std_deg: float = 3.0):
        std = torch.full((skeleton.num_dofs,), 0.5 * rotation_std_deg * 3.141592653589793 / 180)
        std[list(skeleton.translation_dofs)] = 0.01
        super().__init__(std, skeleton.num_dofs, skeleton.lower, skeleton.upper)


class ShiftedOpenPose(OpenPoseJson):
    """A keypoint source of a user's (``data.keypoints.source=<its YAML>``): the recording's
    OpenPose detections moved by ``shift`` pixels (u and v) — a stand-in for a detector."""

    def __init__(self, shift: float = 0.0, folder: str = "auto") -> None:
        super().__init__(folder)
        self.shift = float(shift)

    def read(self, request):
        det = super().read(request)
        for frame in det.people:
            for x in frame:
                seen = x[..., 2] > 0
                x[..., :2] += torch.where(seen[..., None], self.shift, 0.0)
        det.report["shift"] = self.shift
        return det
