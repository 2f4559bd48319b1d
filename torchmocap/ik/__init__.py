"""Inverse kinematics: the analytic sensor-manifold map of Pons-Moll et al. (2010), kinematic flips
(interpretation trees) and limb IK of Sminchisescu & Triggs (2003), the projection of joint
positions onto the skeleton of Hauberg & Pedersen (2011), and fitting a subject (bone lengths and
first poses) to a recording's triangulated keypoints."""

from torchmocap.ik.flip_tree import (
    MAX_TREE_LINKS,
    InterpretationTree,
    flip_patterns,
    interpretation_tree,
)
from torchmocap.ik.keypoint_fit import SEATED, TRUNK_HOLD, KeypointFit, fit_keypoint_subject
from torchmocap.ik.limb import (
    HUMAN31_LIMBS,
    LimbIK,
    LimbIKResult,
    LimbSpec,
    limb_dofs,
    solve_limb,
)
from torchmocap.ik.projection import (
    ProjectionResult,
    SkeletonProjection,
    project_to_skeleton,
)
from torchmocap.ik.rig_fit import fit_rig_to_skeleton
from torchmocap.ik.sensor_manifold import (
    PAPER_SENSORS,
    ManifoldSolution,
    SensorManifold,
    SensorManifoldError,
    sensor_rotations,
)

__all__ = [
    "fit_rig_to_skeleton",
    "HUMAN31_LIMBS",
    "MAX_TREE_LINKS",
    "PAPER_SENSORS",
    "InterpretationTree",
    "KeypointFit",
    "LimbIK",
    "LimbIKResult",
    "LimbSpec",
    "ManifoldSolution",
    "ProjectionResult",
    "SensorManifold",
    "SEATED",
    "SensorManifoldError",
    "TRUNK_HOLD",
    "SkeletonProjection",
    "fit_keypoint_subject",
    "flip_patterns",
    "interpretation_tree",
    "limb_dofs",
    "project_to_skeleton",
    "sensor_rotations",
    "solve_limb",
]
