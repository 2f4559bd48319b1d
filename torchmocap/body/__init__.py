"""Body surfaces: capsule skin (distances, samples, meshes) and the skinned CC0 mesh (LBS)."""

from torchmocap.body.capsules import (
    ANTHROPOMETRIC_RADIUS_RATIOS,
    CapsuleBody,
    anthropometric_radii,
    capsule_distance,
    capsule_endpoints,
    capsules_to_trimesh,
    export_mesh,
    facing_camera,
    rays_blocked_by_capsules,
    sample_capsule_surface,
    segment_closest_points,
    segment_distance,
)
from torchmocap.body.parts import own_parts
from torchmocap.body.skinning import (
    HUMAN31_BONE_MAP,
    HUMAN31_SEGMENTS,
    SkeletonBinding,
    SkinnedBody,
    linear_blend_skinning,
    rotation_between,
)

__all__ = [
    "ANTHROPOMETRIC_RADIUS_RATIOS",
    "HUMAN31_BONE_MAP",
    "HUMAN31_SEGMENTS",
    "CapsuleBody",
    "SkeletonBinding",
    "SkinnedBody",
    "anthropometric_radii",
    "capsule_distance",
    "capsule_endpoints",
    "capsules_to_trimesh",
    "export_mesh",
    "facing_camera",
    "own_parts",
    "rays_blocked_by_capsules",
    "linear_blend_skinning",
    "rotation_between",
    "sample_capsule_surface",
    "segment_closest_points",
    "segment_distance",
]
