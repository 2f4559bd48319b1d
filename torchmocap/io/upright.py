"""Which way is up in a motion file: files whose subject does not stand along +z after reading.

BVH and ASF are Y-up by convention and the readers turn them Z-up; some exporters write Z-up
(or other) axes, and such a clip then lies on the floor — every later step would run on it
without complaint. :func:`upright` looks at the **rest pose** (offsets only, all rotations
identity: the T- or A-pose the skeleton is defined in, standing for every exporter seen) and
measures the direction from the mid-ankle to the head end. Within 45° of +z the clip is left
alone; within 30° of another signed axis the whole clip is turned (:meth:`MotionClip.
change_basis`) by the rotation taking that axis to +z; otherwise nothing is changed and a
warning says the up axis cannot be told. The motion itself is not consulted, so a person lying
or crawling in the clip is never "corrected".
"""

from __future__ import annotations

import math

import torch

__all__ = ["UP_AXES", "rest_up_direction", "upright"]

#: ``up`` settings: ``auto`` (detect from the rest pose), or the file's up axis as written:
#: ``y`` (the BVH/ASF convention, nothing turned) or ``z`` (a Z-up file).
UP_AXES = ("auto", "y", "z")

_UPRIGHT_DEG = 45.0
_AXIS_DEG = 30.0


def rest_up_direction(clip, skeleton_map=None) -> torch.Tensor | None:
    """Unit vector ``(3,)`` from the mid-ankle to ``head_top`` in the rest pose, in the clip's
    world axes; ``None`` when the joints do not map onto human31 or the two coincide."""
    from torchmocap.io.errors import SkeletonMapError
    from torchmocap.io.skeleton_maps import _structure, map_joints

    try:
        idx = map_joints(clip, skeleton_map)
    except SkeletonMapError:
        return None
    _, pos = _structure(clip, clip.joint_names)  # rest positions (J, 3), float64
    d = pos[idx["head_top"]] - 0.5 * (pos[idx["l_ankle"]] + pos[idx["r_ankle"]])
    n = float(d.norm())
    return d / n if n > 1e-9 else None


def _to_z(a: torch.Tensor) -> torch.Tensor:
    """Rotation taking the signed axis ``a`` to +z (the smallest one; 180° about x for -z)."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    if float(a @ z) > 0.5:
        return torch.eye(3, dtype=torch.float64)
    if float(a @ z) < -0.5:
        return torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    k = torch.linalg.cross(a, z)  # unit: a is perpendicular to z
    K = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]],
                     dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + K + K @ K  # Rodrigues, 90 degrees


def upright(clip, up: str = "auto", skeleton_map=None):
    """``clip`` standing along +z, and what was done.

    Args:
        clip: a :class:`~torchmocap.io.MotionClip` as read (the Y-up file convention applied).
        up: ``"auto"`` (detect from the rest pose), ``"y"`` (trust the Y-up convention: the
            clip is returned as it is) or ``"z"`` (the file is Z-up: the reader's Y-up turn is
            undone).
        skeleton_map: the map that finds ankles and head (default: detected or guessed).

    Returns:
        ``(clip, note)``: ``note`` is ``None`` when nothing was changed or detected, else a
        sentence for a warning (the clip was turned, or its up axis cannot be told).

    Raises:
        ValueError: ``up`` is not one of :data:`UP_AXES`.
    """
    from torchmocap.io.motion import Y_UP_TO_Z_UP

    if up not in UP_AXES:
        raise ValueError(f"up: expected one of {UP_AXES}, got {up!r}")
    if up == "y":
        return clip, None
    if up == "z":
        return clip.change_basis(Y_UP_TO_Z_UP.T), None
    u = rest_up_direction(clip, skeleton_map)
    if u is None:
        return clip, None
    names = ("+x", "-x", "+y", "-y", "+z", "-z")
    axes = torch.cat([torch.eye(3, dtype=torch.float64), -torch.eye(3, dtype=torch.float64)])
    axes = axes[[0, 3, 1, 4, 2, 5]]
    cos = axes @ u
    k = int(cos.argmax())
    if names[k] == "+z" and float(cos[k]) >= math.cos(math.radians(_UPRIGHT_DEG)):
        return clip, None
    angle = math.degrees(math.acos(max(-1.0, min(1.0, float(cos[4])))))
    if float(cos[k]) < math.cos(math.radians(_AXIS_DEG)):
        return clip, (f"the rest pose's ankle-to-head direction is {angle:.0f} deg from +z and "
                      "near no axis: the up axis cannot be told; the clip is left as read (pass "
                      "up='y' or 'z' to say how the file is written)")
    G = _to_z(axes[k])
    how = " (the file is Z-up)" if names[k] == "-y" else ""
    return clip.change_basis(G), (
        f"the rest pose stands along {names[k]} after the Y-up reading{how}; the clip was "
        "turned to stand along +z (pass up='y' to keep it as read)")
