"""Synthetic BVH files of skeleton families that no built-in map knows (test helper).

:func:`unseen_family_clip` builds a 22-joint skeleton with human31's geometry — plus a split
spine (``Spine1``, ``Chest``) and clavicles — whose joints are named by one of several common
conventions, drives it with human31 poses (so a correct mapping fits with ~zero residual) and
returns the clip; :func:`write_unseen_family_bvh` writes it as BVH. Leaves that are not end
sites (the toes) get zero-length end sites, as BVH exporters write them.
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchmocap.io import MotionClip, write_bvh
from torchmocap.skeleton import Skeleton, human31

# role -> name, per convention; roles are human31 joints plus the extra joints spine1, chest,
# l_clavicle, r_clavicle; "{s}" is the side word of the convention.
_ROLES_BASE = {
    "pelvis": "Hips", "spine": "Spine", "spine1": "Spine1", "chest": "Chest", "neck": "Neck",
    "head": "Head", "clavicle": "Shoulder", "shoulder": "UpperArm", "elbow": "LowerArm",
    "wrist": "Hand", "hip": "UpperLeg", "knee": "LowerLeg", "ankle": "Foot", "toe": "Toes",
}


def _suffix(sep: str, left: str = "L", right: str = "R"):
    return lambda part, side: f"{part}{sep}{left if side == 'l' else right}"


def _prefix(sep: str, left: str = "L", right: str = "R"):
    return lambda part, side: f"{left if side == 'l' else right}{sep}{part}"


#: convention name -> (sided namer, {role: part name} overrides, torso names)
CONVENTIONS = {
    # Blender/Unity-style "UpperArm_L", "LowerLeg_R", "Toes_L"
    "suffix_underscore": (_suffix("_"), {}),
    # Blender rigify-style lower case with ".L"
    "suffix_dot": (_suffix("."), {
        "pelvis": "pelvis", "spine": "spine", "spine1": "spine.001", "chest": "chest",
        "neck": "neck", "head": "head", "clavicle": "shoulder", "shoulder": "upper_arm",
        "elbow": "forearm", "wrist": "hand", "hip": "thigh", "knee": "shin", "ankle": "foot",
        "toe": "toe"}),
    # Mixamo: "mixamorig:LeftArm" (the clavicle is "LeftShoulder")
    "mixamo": (lambda part, side: f"mixamorig:{'Left' if side == 'l' else 'Right'}{part}", {
        "pelvis": "mixamorig:Hips", "spine": "mixamorig:Spine", "spine1": "mixamorig:Spine1",
        "chest": "mixamorig:Spine2", "neck": "mixamorig:Neck", "head": "mixamorig:Head",
        "clavicle": "Shoulder", "shoulder": "Arm", "elbow": "ForeArm", "wrist": "Hand",
        "hip": "UpLeg", "knee": "Leg", "ankle": "Foot", "toe": "ToeBase"}),
    # Unreal-style "upperarm_l", "calf_r", "ball_l"
    "unreal": (_suffix("_", "l", "r"), {
        "pelvis": "pelvis", "spine": "spine_01", "spine1": "spine_02", "chest": "spine_03",
        "neck": "neck_01", "head": "head", "clavicle": "clavicle", "shoulder": "upperarm",
        "elbow": "lowerarm", "wrist": "hand", "hip": "thigh", "knee": "calf", "ankle": "foot",
        "toe": "ball"}),
    # "l_" prefixes
    "prefix_underscore": (_prefix("_", "l", "r"), {
        "pelvis": "root", "spine": "torso", "spine1": "torso1", "chest": "chest",
        "clavicle": "collar", "shoulder": "upperarm", "elbow": "forearm", "wrist": "wrist",
        "hip": "thigh", "knee": "knee", "ankle": "ankle", "toe": "toe"}),
    # "LThigh", "RShin" (letter prefix, CamelCase)
    "prefix_letter": (_prefix(""), {
        "clavicle": "Collar", "shoulder": "Shoulder", "elbow": "ForeArm", "wrist": "Hand",
        "hip": "Thigh", "knee": "Shin", "ankle": "Foot", "toe": "Toe"}),
    # "LeftUpperArm", "RightCalf"
    "left_right_words": (_prefix("", "Left", "Right"), {
        "pelvis": "Pelvis", "clavicle": "Clavicle", "shoulder": "UpperArm", "elbow": "Forearm",
        "wrist": "Hand", "hip": "Thigh", "knee": "Calf", "ankle": "Ankle", "toe": "Ball"}),
}


def names_for(convention: str) -> dict[str, str]:
    """role (human31 joint or spine1/chest/l_clavicle/r_clavicle) -> joint name."""
    namer, parts = CONVENTIONS[convention]
    parts = {**_ROLES_BASE, **parts}
    out = {r: parts[r] for r in ("pelvis", "spine", "spine1", "chest", "neck", "head")}
    for sd in ("l", "r"):
        for role in ("clavicle", "shoulder", "elbow", "wrist", "hip", "knee", "ankle", "toe"):
            out[f"{sd}_{role}"] = namer(parts[role], sd)
    return out


def unseen_family_skeleton(convention: str, end_length: float = 0.0,
                           rename: dict[str, str] | None = None) -> Skeleton:
    """The 22-joint skeleton (plus end sites) in ``convention``; ``end_length`` is the length
    of the head and hand end sites (0: zero-length end sites, as in CMU21 exports)."""
    n = {**names_for(convention), **(rename or {})}
    spec = {j["name"]: j for j in human31().to_dict()["joints"]}
    joints = []

    def add(role: str, parent: str | None, offset, src: str | None = None) -> None:
        j = {"name": n.get(role, role), "parent": None if parent is None else n[parent],
             "offset": [float(v) for v in offset]}
        if src is not None and "axes" in spec[src]:
            j.update(axes=spec[src]["axes"], dof_names=spec[src]["dof_names"],
                     limits=spec[src]["limits"])
        joints.append(j)

    add("pelvis", None, spec["pelvis"]["offset"], "pelvis")
    add("spine", "pelvis", spec["spine"]["offset"], "spine")
    add("spine1", "spine", [0.0, 0.0, 0.15])
    add("chest", "spine1", [0.0, 0.0, 0.15])
    add("neck", "chest", [0.0, 0.0, 0.14], "neck")  # 0.15 + 0.15 + 0.14 = human31's 0.44
    add("head", "neck", spec["head"]["offset"], "head")
    n["head_end"] = f"{n['head']}_end"
    add("head_end", "head", [0.0, 0.0, 0.12 if end_length else 0.0])
    for sd, x in (("l", 1.0), ("r", -1.0)):
        add(f"{sd}_clavicle", "chest", [0.05 * x, 0.0, 0.04])
        add(f"{sd}_shoulder", f"{sd}_clavicle", [0.13 * x, 0.0, 0.02], f"{sd}_shoulder")
        add(f"{sd}_elbow", f"{sd}_shoulder", spec[f"{sd}_elbow"]["offset"], f"{sd}_elbow")
        add(f"{sd}_wrist", f"{sd}_elbow", spec[f"{sd}_wrist"]["offset"], f"{sd}_wrist")
        n[f"{sd}_hand_end"] = f"{n[f'{sd}_wrist']}_end"
        add(f"{sd}_hand_end", f"{sd}_wrist", [0.0, 0.0, -end_length])
    for sd in ("l", "r"):
        add(f"{sd}_hip", "pelvis", spec[f"{sd}_hip"]["offset"], f"{sd}_hip")
        add(f"{sd}_knee", f"{sd}_hip", spec[f"{sd}_knee"]["offset"], f"{sd}_knee")
        add(f"{sd}_ankle", f"{sd}_knee", spec[f"{sd}_ankle"]["offset"], f"{sd}_ankle")
        add(f"{sd}_toe", f"{sd}_ankle", spec[f"{sd}_toe"]["offset"])
    sk = Skeleton.from_dict({"name": f"unseen_{convention}", "joints": joints})
    return sk.double()


def human31_motion(frames: int, seed: int = 0) -> torch.Tensor:
    """``(frames, 31)`` smooth human31 poses inside the joint limits (float64)."""
    sk = human31().double()
    g = torch.Generator().manual_seed(seed)
    lo = torch.where(torch.isinf(sk.lower), torch.full_like(sk.lower, -0.6), sk.lower)
    hi = torch.where(torch.isinf(sk.upper), torch.full_like(sk.upper, 0.6), sk.upper)
    a = torch.rand(2, sk.num_dofs, generator=g, dtype=torch.float64)
    t = torch.linspace(0, 1, frames, dtype=torch.float64)[:, None]
    u = (1 - t) * a[0] + t * a[1]  # a straight path through the box of limits
    theta = lo + (hi - lo) * (0.2 + 0.6 * u)
    theta[:, :3] = torch.tensor([0.1, -0.2, 0.0], dtype=torch.float64) + 0.05 * t
    return sk.clamp(theta)


def unseen_family_clip(convention: str, frames: int = 8, end_length: float = 0.0,
                       rename: dict[str, str] | None = None) -> MotionClip:
    """The skeleton of :func:`unseen_family_skeleton` driven by :func:`human31_motion`."""
    sk = unseen_family_skeleton(convention, end_length, rename)
    assert sk.num_dofs == 31
    return MotionClip.from_skeleton(sk, human31_motion(frames), fps=30.0, skeleton_family=None)


def write_unseen_family_bvh(path: str | Path, convention: str, frames: int = 8,
                            end_length: float = 0.0, unit: float = 0.01,
                            rename: dict[str, str] | None = None) -> Path:
    """Write :func:`unseen_family_clip` as a BVH in ``unit`` metres per file unit (cm)."""
    return write_bvh(path, unseen_family_clip(convention, frames, end_length, rename), unit=unit,
                     precision=6)
