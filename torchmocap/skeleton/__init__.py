"""Articulated skeletons with batched product-of-exponentials forward kinematics."""

from torchmocap.skeleton.presets import PRESETS, human31, preset, upper_body
from torchmocap.skeleton.skeleton import Kinematics, Skeleton, SkeletonError
from torchmocap.skeleton.urdf import (
    pk_theta,
    skeleton_to_urdf,
    to_pytorch_kinematics_chain,
    write_urdf,
)

__all__ = [
    "Kinematics",
    "PRESETS",
    "Skeleton",
    "SkeletonError",
    "human31",
    "pk_theta",
    "preset",
    "skeleton_to_urdf",
    "to_pytorch_kinematics_chain",
    "upper_body",
    "write_urdf",
]
