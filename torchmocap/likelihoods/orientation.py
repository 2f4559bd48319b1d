"""Sensor-orientation term (the "S" of the GS and LS baselines of Pons-Moll et al. 2010).

``V_ori = mean_s d(R_TB,s(theta) R_BS,s, R_TS,s)^k`` with ``d`` the geodesic angle (radians,
atan2 form) and ``k = 1`` (the paper's "increasing linear function of the angular error" for
GS) or ``k = 2``, ``R_TB,s`` the model's global frame of the bone carrying sensor ``s``, ``R_BS,s``
its calibrated sensor-to-bone offset and ``R_TS,s`` the measured sensor orientation.
Shapes: ``P`` particles, ``S`` sensors.
"""

from __future__ import annotations

import math

import torch

from torchmocap.geometry import geodesic_angle
from torchmocap.likelihoods.base import Likelihood

__all__ = ["orientation_energy", "OrientationLikelihood", "sensor_evidence"]


def sensor_evidence(valid: torch.Tensor | None) -> bool:
    """Whether a frame's sensor samples hold evidence: ``valid (S,)`` has a sample that was not
    dropped (None: all valid)."""
    return valid is None or bool(valid.any())


def orientation_energy(bone_rotations: torch.Tensor, offsets: torch.Tensor,
                       measured: torch.Tensor, valid: torch.Tensor | None = None,
                       power: int = 2) -> torch.Tensor:
    """``V_ori (P,)`` from model bone frames ``(P, S, 3, 3)``, offsets ``R_BS (S, 3, 3)`` and
    measured ``R_TS (S, 3, 3)``; ``valid (S,)`` masks dropped samples (with none valid every pose
    gets the largest cost, ``pi^power``: no evidence is not a perfect match); ``power`` 1
    (linear in the angle) or 2 (squared)."""
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
    if not bool(valid.any()):  # every sample dropped: uninformative, never a perfect 0
        return torch.full(cost.shape[:-1], math.pi ** power, dtype=cost.dtype,
                          device=cost.device)
    return (cost * w).sum(-1) / w.sum()


class OrientationLikelihood(Likelihood):
    """Sensor-orientation energy ``V_ori`` of the tracking IMUs (the "S" of GS and LS).

    Args:
        manifold: the :class:`~torchmocap.ik.SensorManifold` of the tracking sensors: which bone
            carries each sensor, and the calibration ``R_SB`` (eq. 8) set when tracking starts.
        power: 1 (linear in the angle: the paper's GS cost) or 2 (squared).

    ``requires = ("imu",)``; ``prepare(frame)`` reads the tracking sensors' orientations
    ``frame.imu (S, 4)`` (or ``(S, 3, 3)``) and ``frame.imu_valid (S,)``.
    """

    requires = ("imu",)

    def __init__(self, manifold, power: int = 2):
        super().__init__()
        if power not in (1, 2):
            raise ValueError(f"power: expected 1 (linear) or 2 (squared), got {power!r}")
        self.manifold = manifold
        self.power = int(power)

    def prepare(self, frame) -> tuple[torch.Tensor, torch.Tensor | None]:
        from torchmocap.ik.sensor_manifold import sensor_rotations

        R_ts = sensor_rotations(frame.imu, self.manifold.num_sensors)
        valid = getattr(frame, "imu_valid", None)
        return R_ts.to(self.manifold.sensor_to_bone.dtype), valid

    def evidence(self, observation) -> bool:
        return sensor_evidence(observation[1])

    def energy(self, poses, observation) -> torch.Tensor:
        R_ts, valid = observation
        m = self.manifold
        R = poses.kinematics.rotations.index_select(-3, m._bone_index.to(R_ts.device))
        return orientation_energy(R, m.sensor_to_bone.transpose(-1, -2), R_ts, valid,
                                  self.power)

    def extra_repr(self) -> str:
        return f"power={self.power}, sensors={self.manifold.sensor_names}"
