"""Articulated skeletons with batched product-of-exponentials forward kinematics, and where a
keypoint detector's keypoints sit on them (keypoint maps)."""

from torchmocap.skeleton.keypoints import (
    KeypointMap,
    KeypointMapError,
    keypoint_positions,
    known_keypoint_formats,
    load_keypoint_map,
)
from torchmocap.skeleton.presets import PRESETS, human31, preset, upper_body
from torchmocap.skeleton.skeleton import Kinematics, Skeleton, SkeletonError
from torchmocap.skeleton.urdf import (
    pk_theta,
    skeleton_to_urdf,
    to_pytorch_kinematics_chain,
    write_urdf,
)

__all__ = [
    "KeypointMap",
    "KeypointMapError",
    "Kinematics",
    "PRESETS",
    "Skeleton",
    "SkeletonError",
    "human31",
    "keypoint_positions",
    "known_keypoint_formats",
    "load_keypoint_map",
    "pk_theta",
    "preset",
    "skeleton_to_urdf",
    "to_pytorch_kinematics_chain",
    "upper_body",
    "write_urdf",
]
