"""Sensor-orientation term (the "S" of the GS and LS baselines of Pons-Moll et al. 2010).

``V_ori = mean_s d(R_TB,s(theta) R_BS,s, R_TS,s)^k`` with ``d`` the geodesic angle (radians,
atan2 form) and ``k = 1`` (the paper's "increasing linear function of the angular error" for
GS) or ``k = 2``, ``R_TB,s`` the model's global frame of the bone carrying sensor ``s``, ``R_BS,s``
its calibrated sensor-to-bone offset and ``R_TS,s`` the measured sensor orientation.
Shapes: ``P`` particles, ``S`` sensors.
"""

from __future__ import annotations

import torch
from torch import nn

from torchmocap.geometry import geodesic_angle

__all__ = ["orientation_energy", "OrientationLikelihood"]


def orientation_energy(bone_rotations: torch.Tensor, offsets: torch.Tensor,
                       measured: torch.Tensor, valid: torch.Tensor | None = None,
                       power: int = 2) -> torch.Tensor:
    """``V_ori (P,)`` from model bone frames ``(P, S, 3, 3)``, offsets ``R_BS (S, 3, 3)`` and
    measured ``R_TS (S, 3, 3)``; ``valid (S,)`` masks dropped samples; ``power`` 1 (linear in
    the angle) or 2 (squared)."""
    if bone_rotations.shape[-3:] != measured.shape[-3:]:
        raise ValueError(f"measured: expected shape {tuple(bone_rotations.shape[-3:])}, got "
                         f"{tuple(measured.shape)}")
    if power not in (1, 2):
        raise ValueError(f"power: expected 1 (linear) or 2 (squared), got {power!r}")
    ang = geodesic_angle(bone_rotations @ offsets.to(bone_rotations.dtype),
                         measured.to(bone_rotations.dtype))
    cost = ang if power == 1 else ang * ang
    if valid is None:
        return cost.mean(-1)
    w = valid.to(ang.dtype)
    return (cost * w).sum(-1) / w.sum().clamp_min(1)


class OrientationLikelihood(nn.Module):
    """Log-likelihood ``-weight * V_ori`` for sensors on the named bones (joint frames)."""

    def __init__(self, skeleton, bones: list[str], weight: float = 1.0, power: int = 2):
        super().__init__()
        if power not in (1, 2):
            raise ValueError(f"power: expected 1 (linear) or 2 (squared), got {power!r}")
        self.power = int(power)
        self.skeleton = skeleton
        self.bones = list(bones)
        self.bone_index = [skeleton.joint_index(b) for b in self.bones]
        self.weight = float(weight)

    def energy(self, theta, offsets, measured, valid=None):
        R = self.skeleton(theta, check_finite=False).rotations[..., self.bone_index, :, :]
        return orientation_energy(R, offsets, measured, valid, self.power)

    def forward(self, theta, offsets, measured, valid=None):
        return -self.weight * self.energy(theta, offsets, measured, valid)
