"""Rotation and rigid-motion geometry: SO(3)/SE(3) maps, quaternions (w, x, y, z), twists."""

from torchmocap.geometry.angles import wrap_angle
from torchmocap.geometry.flips import RaySphereIntersection, flip_child, ray_sphere_intersections
from torchmocap.geometry.quaternions import (
    axis_angle_to_quaternion,
    matrix_to_quaternion,
    quaternion_angle,
    quaternion_canonical,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_slerp,
    quaternion_to_axis_angle,
    quaternion_to_matrix,
    random_quaternion,
)
from torchmocap.geometry.rotations import (
    axis_angle_rotation,
    geodesic_angle,
    hat,
    random_rotation_matrix,
    rotation_mean,
    so3_exp,
    so3_log,
    vee,
)
from torchmocap.geometry.twists import make_transform, revolute_twist, se3_exp, transform_points

__all__ = [
    "RaySphereIntersection",
    "axis_angle_rotation",
    "axis_angle_to_quaternion",
    "flip_child",
    "geodesic_angle",
    "hat",
    "make_transform",
    "matrix_to_quaternion",
    "quaternion_angle",
    "quaternion_canonical",
    "quaternion_conjugate",
    "quaternion_multiply",
    "quaternion_slerp",
    "quaternion_to_axis_angle",
    "quaternion_to_matrix",
    "random_quaternion",
    "random_rotation_matrix",
    "ray_sphere_intersections",
    "revolute_twist",
    "rotation_mean",
    "se3_exp",
    "so3_exp",
    "so3_log",
    "transform_points",
    "vee",
    "wrap_angle",
]
