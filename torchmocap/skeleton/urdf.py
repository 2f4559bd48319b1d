"""URDF interoperability through pytorch-kinematics.

A :class:`~torchmocap.skeleton.Skeleton` joint with ``k`` revolute axes becomes ``k`` one-DoF URDF
joints chained through massless dummy links (URDF has no ball joints); the root becomes three
prismatic joints followed by its revolute axes; 0-DoF joints become ``fixed`` joints. Every
Skeleton joint ends in a link of the same name, so frames can be compared one to one. Unlimited
revolute DoFs are exported as ``continuous`` joints.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import torch

from torchmocap.skeleton.skeleton import Skeleton

__all__ = ["skeleton_to_urdf", "write_urdf", "to_pytorch_kinematics_chain", "pk_theta"]


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in v)


def skeleton_to_urdf(skeleton: Skeleton) -> str:
    """URDF XML text of ``skeleton``; its actuated joints appear in ``theta`` order."""
    robot = ET.Element("robot", name=skeleton.name)
    ET.SubElement(robot, "link", name="world")
    lo, hi = skeleton.lower.tolist(), skeleton.upper.tolist()
    offsets = skeleton.offsets.detach().double().cpu().tolist()
    dof_names = skeleton.dof_names

    def add_joint(name, jtype, parent, child, xyz=(0, 0, 0), axis=None, dof=None):
        ET.SubElement(robot, "link", name=child)
        j = ET.SubElement(robot, "joint", name=name, type=jtype)
        ET.SubElement(j, "parent", link=parent)
        ET.SubElement(j, "child", link=child)
        ET.SubElement(j, "origin", xyz=_fmt(xyz), rpy="0 0 0")
        if axis is not None:
            ET.SubElement(j, "axis", xyz=_fmt(axis))
        if dof is not None and jtype in ("revolute", "prismatic"):
            lower = lo[dof] if math.isfinite(lo[dof]) else -1e6
            upper = hi[dof] if math.isfinite(hi[dof]) else 1e6
            ET.SubElement(j, "limit", lower=repr(lower), upper=repr(upper),
                          effort="100", velocity="10")

    for ji, name in enumerate(skeleton.joint_names):
        parent = "world" if skeleton.parents[ji] < 0 else skeleton.joint_names[skeleton.parents[ji]]
        dofs = skeleton.joint_dofs(name)
        axes = skeleton.joint_axes[ji]
        steps = []  # (type, axis, dof)
        if ji == 0 and skeleton.root_translation:
            for k, e in enumerate(([1, 0, 0], [0, 1, 0], [0, 0, 1])):
                steps.append(("prismatic", e, dofs[k]))
            dofs = dofs[3:]
        for a, d in zip(axes, dofs):
            jt = "revolute" if (math.isfinite(lo[d]) or math.isfinite(hi[d])) else "continuous"
            steps.append((jt, a, d))
        if not steps:
            add_joint(f"{name}__fixed", "fixed", parent, name, offsets[ji])
            continue
        prev = parent
        for k, (jt, a, d) in enumerate(steps):
            child = name if k == len(steps) - 1 else f"{name}__{k}"
            add_joint(dof_names[d], jt, prev, child, offsets[ji] if k == 0 else (0, 0, 0), a, d)
            prev = child
    ET.indent(robot)
    return ET.tostring(robot, encoding="unicode")


def write_urdf(skeleton: Skeleton, path: str | Path) -> Path:
    """Write the URDF of ``skeleton`` to ``path`` atomically (temp file, then rename)."""
    from torchmocap.atomic import write_text_atomic

    return write_text_atomic(path, skeleton_to_urdf(skeleton))


def to_pytorch_kinematics_chain(skeleton: Skeleton, dtype=torch.float32, device="cpu"):
    """A ``pytorch_kinematics`` chain equivalent to ``skeleton``.

    Its joint parameter order equals ``skeleton.dof_names`` (checked); use :func:`pk_theta` to be
    explicit. Note pytorch-kinematics parses URDF offsets in float32 even for float64 chains.
    """
    import pytorch_kinematics as pk

    chain = pk.build_chain_from_urdf(skeleton_to_urdf(skeleton).encode())
    chain = chain.to(dtype=dtype, device=device)
    names = chain.get_joint_parameter_names()
    if sorted(names) != sorted(skeleton.dof_names):
        raise RuntimeError(f"URDF export lost DoFs: {sorted(set(skeleton.dof_names) - set(names))}")
    return chain


def pk_theta(chain, skeleton: Skeleton, theta: torch.Tensor) -> torch.Tensor:
    """Reorder ``theta (..., D)`` from skeleton DoF order into the chain's joint order."""
    names = chain.get_joint_parameter_names()
    idx = torch.tensor([skeleton.dof_index(n) for n in names], device=theta.device)
    return theta[..., idx]
