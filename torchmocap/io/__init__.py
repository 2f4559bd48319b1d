"""Motion-capture file I/O: BVH and ASF/AMC readers, BVH writer, TRC marker reader, skeleton
maps."""

from torchmocap.io.asf import AsfSkeleton, read_amc, read_asf, read_asf_amc
from torchmocap.io.bvh import read_bvh, write_bvh
from torchmocap.io.errors import MotionFormatError, SkeletonMapError
from torchmocap.io.load import bundled_clip_path, find_asf, load_motion
from torchmocap.io.motion import Y_UP_TO_Z_UP, MotionClip
from torchmocap.io.skeleton_maps import (
    HUMAN31_JOINTS,
    JointGuess,
    SkeletonMap,
    chain_height,
    detect_family,
    guess_joint_map,
    guess_joints,
    guessed_joints,
    human31_positions,
    joint_map_report,
    known_families,
    load_skeleton_map,
    map_joints,
    resolve_skeleton_map,
    unmapped_joints,
)
from torchmocap.io.trc import TRC_Y_UP_TO_Z_UP, TrcData, read_trc, trc_to_z_up

__all__ = [
    "AsfSkeleton",
    "bundled_clip_path",
    "find_asf",
    "load_motion",
    "read_amc",
    "read_asf",
    "read_asf_amc",
    "HUMAN31_JOINTS",
    "JointGuess",
    "MotionClip",
    "MotionFormatError",
    "SkeletonMap",
    "SkeletonMapError",
    "TRC_Y_UP_TO_Z_UP",
    "TrcData",
    "Y_UP_TO_Z_UP",
    "chain_height",
    "detect_family",
    "guess_joint_map",
    "guess_joints",
    "guessed_joints",
    "human31_positions",
    "joint_map_report",
    "known_families",
    "load_skeleton_map",
    "map_joints",
    "read_bvh",
    "read_trc",
    "resolve_skeleton_map",
    "trc_to_z_up",
    "unmapped_joints",
    "write_bvh",
]
