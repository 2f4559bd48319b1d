"""Inverse kinematics: the analytic sensor-manifold map of Pons-Moll et al. (2010)."""

from torchmocap.ik.sensor_manifold import (
    PAPER_SENSORS,
    ManifoldSolution,
    SensorManifold,
    SensorManifoldError,
    sensor_rotations,
)

__all__ = [
    "PAPER_SENSORS",
    "ManifoldSolution",
    "SensorManifold",
    "SensorManifoldError",
    "sensor_rotations",
]
