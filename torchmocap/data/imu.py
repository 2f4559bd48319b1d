"""IMU orientations and their placement on the body: :class:`ImuData` (a modality of a
:class:`~torchmocap.data.Sequence`). Synthetic sensors with the error sources of Pons-Moll et al.
(2010) are made by :func:`torchmocap.data.synthetic.imu.synthesize_imu`.

Quaternions are w, x, y, z with ``w >= 0``. Shapes: ``T`` frames, ``S`` sensors.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["ImuData", "SensorPlacementError", "resolve_sensors"]

class SensorPlacementError(ValueError):
    """A sensor is placed on a bone the skeleton does not have."""


@dataclass
class ImuData:
    """IMU orientations and their placement.

    Attributes:
        names: ``S`` sensor names.
        bones: ``S`` joint names (bone frames) the sensors are strapped to.
        tracking: ``(S,)`` bool, True for tracking sensors (False: validation).
        quaternions: ``(T, S, 4)`` measured orientations ``q_TS`` (w, x, y, z).
        valid: ``(T, S)`` bool, False where the sample was dropped (value held).
        clean: ``(T, S, 4)`` noise-free orientations ``R_TB · R_BS``.
        offsets: ``(S, 4)`` sensor-to-bone offsets ``R_BS``.
        misalignment: ``(4,)`` inertial-to-tracking frame error ``R_mis``.
        drift_rates: ``(S,)`` heading drift rates (rad/s, signed).
        desync_frames: temporal offset applied (frames).
    """

    names: list[str]
    bones: list[str]
    tracking: Tensor
    quaternions: Tensor
    valid: Tensor
    clean: Tensor
    offsets: Tensor
    misalignment: Tensor
    drift_rates: Tensor
    desync_frames: float = 0.0

    @property
    def num_sensors(self) -> int:
        return len(self.names)

    def select(self, which: str = "tracking") -> ImuData:
        """The ``tracking`` or ``validation`` sensors only."""
        if which not in ("tracking", "validation"):
            raise ValueError(f"which: expected 'tracking' or 'validation', got {which!r}")
        keep = self.tracking if which == "tracking" else ~self.tracking
        idx = keep.nonzero().squeeze(-1)
        return ImuData([self.names[i] for i in idx.tolist()],
                       [self.bones[i] for i in idx.tolist()], self.tracking[idx],
                       self.quaternions[:, idx], self.valid[:, idx], self.clean[:, idx],
                       self.offsets[idx], self.misalignment, self.drift_rates[idx],
                       self.desync_frames)


def resolve_sensors(sensors: dict[str, str], joint_names: list[str]) -> list[int]:
    """Joint index of each sensor's bone; raises :class:`SensorPlacementError` naming it."""
    out = []
    for name, bone in sensors.items():
        if bone not in joint_names:
            raise SensorPlacementError(
                f"imu.sensors[{name!r}]: unknown bone {bone!r}; expected one of {joint_names}")
        out.append(joint_names.index(bone))
    return out
