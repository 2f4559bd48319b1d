"""Skinned CC0 body mesh (MakeHuman/MPFB2, decimated) with linear blend skinning.

The bundled asset ``torchmocap/assets/body/makehuman_cc0_decimated.npz`` (built by
:mod:`torchmocap.body.asset_build`) holds a ~4500-vertex triangulated skin in the torchmocap world
frame (Z-up metres, facing −y, left at +x, MakeHuman rest pose = A-pose with the arms ~45° down,
origin near the pelvis, soles at z ≈ −0.82), top-4 LBS weights over the 31 CMU-MB bones, the
bones' rest head/tail points and every joint cube's centre.

Two ways to pose it:

* :meth:`SkinnedBody.pose` — the mesh's own 31-bone rig: global bone rotations relative to rest
  (identity = rest) plus the root (``Hips`` head) position; bone heads follow by FK.
* :meth:`SkinnedBody.pose_from_skeleton` — driven by a human31
  :class:`~torchmocap.skeleton.Skeleton` pose. Each mesh bone is moved by the human31 joint
  whose frame carries it (:data:`HUMAN31_BONE_MAP`). For each such joint ``j`` a rest
  alignment ``M_j`` maps the mesh's segment onto the skeleton's: it rotates the mesh bone
  direction (joint cube → next joint cube) onto the skeleton's rest bone direction, scales
  along the bone to the skeleton's bone length and across it by the global stature ratio.
  The LBS transform is ``A_j = G_j(θ) · [M_j, −M_j m_j]`` (``m_j`` the mesh joint centre),
  i.e. ``x ↦ p_j(θ) + R_j(θ) M_j (x − m_j)``, so mesh joint centres land on the skeleton's
  joints for every pose.

Shapes: ``V`` vertices, ``Bn`` mesh bones, ``*`` batch dims (particles).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

__all__ = [
    "ASSET_PATH",
    "HUMAN31_BONE_MAP",
    "HUMAN31_SEGMENTS",
    "SkeletonBinding",
    "SkinnedBody",
    "linear_blend_skinning",
    "rotation_between",
]

ASSET_PATH = Path(__file__).resolve().parents[1] / "assets" / "body" / \
    "makehuman_cc0_decimated.npz"

#: mesh bone (CMU-MB name) → human31 joint whose global frame moves it
HUMAN31_BONE_MAP: dict[str, str] = {
    "Hips": "pelvis", "LHipJoint": "pelvis", "RHipJoint": "pelvis",
    "LowerBack": "spine", "Spine": "spine", "Spine1": "spine",
    "LeftShoulder": "spine", "RightShoulder": "spine",
    "Neck": "neck", "Neck1": "neck", "Head": "neck",
    "LeftArm": "l_shoulder", "RightArm": "r_shoulder",
    "LeftForeArm": "l_elbow", "LeftHand": "l_elbow", "LThumb": "l_elbow",
    "LeftFingerBase": "l_elbow", "LeftHandFinger1": "l_elbow",
    "RightForeArm": "r_elbow", "RightHand": "r_elbow", "RThumb": "r_elbow",
    "RightFingerBase": "r_elbow", "RightHandFinger1": "r_elbow",
    "LeftUpLeg": "l_hip", "RightUpLeg": "r_hip",
    "LeftLeg": "l_knee", "RightLeg": "r_knee",
    "LeftFoot": "l_ankle", "LeftToeBase": "l_ankle",
    "RightFoot": "r_ankle", "RightToeBase": "r_ankle",
}

#: human31 joint → (mesh joint cube at the joint, mesh cube at the segment's end,
#: skeleton joint at the segment's end); ``None`` ends = no rest rotation (pelvis)
HUMAN31_SEGMENTS: dict[str, tuple[str, str | None, str | None]] = {
    "pelvis": ("joint-pelvis", None, None),
    "spine": ("joint-spine-3", "joint-neck", "neck"),
    "neck": ("joint-neck", "joint-head-2", "head_top"),
    **{f"{s}_{joint}": (f"joint-{s}-{cube}", f"joint-{s}-{end_cube}", f"{s}_{end}")
       for joint, cube, end_cube, end in (("shoulder", "shoulder", "elbow", "elbow"),
                                           ("elbow", "elbow", "hand", "wrist"),
                                           ("hip", "upper-leg", "knee", "knee"),
                                           ("knee", "knee", "ankle", "ankle"),
                                           ("ankle", "ankle", "toe-3-1", "toe"))
       for s in ("l", "r")},
}

#: stature reference points: (mesh top cube, skeleton top joint, ankle pairs)
_STATURE = ("joint-head-2", "head_top", [("joint-l-ankle", "l_ankle"),
                                         ("joint-r-ankle", "r_ankle")])


def rotation_between(a: Tensor, b: Tensor) -> Tensor:
    """Minimal rotation ``(*, 3, 3)`` taking unit vector ``a (*, 3)`` onto unit vector ``b``.

    Antiparallel inputs get a half turn about an axis perpendicular to ``a``.
    """
    a = a / a.norm(dim=-1, keepdim=True)
    b = b / b.norm(dim=-1, keepdim=True)
    v = torch.linalg.cross(a, b)
    c = (a * b).sum(-1)
    eye = torch.eye(3, dtype=a.dtype, device=a.device).expand(*a.shape[:-1], 3, 3)
    zero = torch.zeros_like(c)
    K = torch.stack([torch.stack([zero, -v[..., 2], v[..., 1]], -1),
                     torch.stack([v[..., 2], zero, -v[..., 0]], -1),
                     torch.stack([-v[..., 1], v[..., 0], zero], -1)], -2)
    anti = c < -1 + 1e-9
    R = eye + K + K @ K / (1 + c).clamp_min(1e-12)[..., None, None]
    if bool(anti.any()):
        ex = torch.tensor([1.0, 0, 0], dtype=a.dtype, device=a.device)
        ey = torch.tensor([0.0, 1, 0], dtype=a.dtype, device=a.device)
        helper = torch.where((a[..., :1].abs() < 0.9), ex, ey)
        u = torch.linalg.cross(a, helper)
        u = u / u.norm(dim=-1, keepdim=True)
        half = 2 * u[..., :, None] * u[..., None, :] - eye
        R = torch.where(anti[..., None, None], half, R)
    return R


def linear_blend_skinning(vertices: Tensor, weights: Tensor, rotations: Tensor,
                          translations: Tensor) -> Tensor:
    """``x'_v = Σ_b w_vb (A_b x_v + a_b)`` for rest vertices and per-bone affine maps.

    Args:
        vertices: ``(V, 3)`` rest vertices.
        weights: ``(V, Bn)`` dense skinning weights (rows sum to 1).
        rotations: ``(*, Bn, 3, 3)`` linear parts (rotations, possibly with scale).
        translations: ``(*, Bn, 3)``.

    Returns:
        ``(*, V, 3)`` posed vertices.
    """
    if weights.shape[0] != vertices.shape[0] or weights.shape[1] != rotations.shape[-3]:
        raise ValueError(f"weights: expected shape ({vertices.shape[0]}, {rotations.shape[-3]}), "
                         f"got {tuple(weights.shape)}")
    A = torch.cat([rotations, translations[..., None]], -1)  # (*, Bn, 3, 4)
    blend = torch.einsum("vb,...bij->...vij", weights.to(A.dtype), A)  # (*, V, 3, 4)
    x = vertices.to(A.dtype)
    return torch.einsum("...vij,vj->...vi", blend[..., :3], x) + blend[..., 3]


@dataclass
class SkeletonBinding:
    """How a skeleton drives the mesh (see :meth:`SkinnedBody.bind`).

    Attributes:
        joint_index: ``(Jm,)`` skeleton joints that carry mesh bones.
        linear: ``(Jm, 3, 3)`` rest alignments ``M_j``.
        mesh_origin: ``(Jm, 3)`` mesh joint centres ``m_j``.
        weights: ``(V, Jm)`` skinning weights summed over the mesh bones of each joint.
        scale: global stature ratio skeleton / mesh.
    """

    joint_index: Tensor
    linear: Tensor
    mesh_origin: Tensor
    weights: Tensor
    scale: float


class SkinnedBody(nn.Module):
    """The bundled CC0 human mesh with linear blend skinning (loads no external data).

    Buffers: ``vertices (V, 3)`` rest (float32), ``faces (F, 3)`` long, ``weights (V, Bn)`` dense,
    ``bone_heads``/``bone_tails (Bn, 3)``, ``joint_centres (Jc, 3)``. Attributes: ``bone_names``,
    ``bone_parents``, ``joint_names`` (joint cubes).

    Example:
        >>> body = SkinnedBody()
        >>> from torchmocap.skeleton import human31
        >>> sk = human31()
        >>> body.pose_from_skeleton(sk, sk.zero_pose((2,))).shape[-1]
        3
    """

    vertices: Tensor
    faces: Tensor
    weights: Tensor
    bone_heads: Tensor
    bone_tails: Tensor
    joint_centres: Tensor

    def __init__(self, asset_path: str | Path | None = None) -> None:
        super().__init__()
        path = Path(asset_path) if asset_path is not None else ASSET_PATH
        if not path.exists():
            raise FileNotFoundError(f"asset_path: body asset not found at {path}")
        with np.load(path) as d:
            V = d["vertices"].shape[0]
            names = [str(s) for s in d["bone_names"]]
            W = np.zeros((V, len(names)), dtype=np.float32)
            np.put_along_axis(W, d["weight_indices"].astype(np.int64), d["weights"], axis=1)
            self.bone_names = names
            self.bone_parents = [int(p) for p in d["bone_parents"]]
            self.joint_names = [str(s) for s in d["joint_names"]]
            self.register_buffer("vertices", torch.from_numpy(d["vertices"].astype(np.float32)))
            self.register_buffer("faces", torch.from_numpy(d["faces"].astype(np.int64)))
            self.register_buffer("weights", torch.from_numpy(W))
            self.register_buffer("bone_heads", torch.from_numpy(d["bone_heads"]))
            self.register_buffer("bone_tails", torch.from_numpy(d["bone_tails"]))
            self.register_buffer("joint_centres", torch.from_numpy(d["joint_centres"]))
        self._bindings: dict[int, tuple[Any, SkeletonBinding, Tensor]] = {}

    # ------------------------------------------------------------------ basics
    @property
    def num_vertices(self) -> int:
        return self.vertices.shape[0]

    @property
    def num_bones(self) -> int:
        return len(self.bone_names)

    def joint_centre(self, name: str) -> Tensor:
        """Rest centre ``(3,)`` of a joint cube (e.g. ``"joint-l-knee"``)."""
        try:
            return self.joint_centres[self.joint_names.index(name)]
        except ValueError:
            raise KeyError(f"unknown joint cube {name!r}") from None

    def bone_weights(self, bone: str) -> Tensor:
        """``(V,)`` skinning weight of one mesh bone."""
        return self.weights[:, self.bone_names.index(bone)]

    # ------------------------------------------------------------------ own rig
    def pose(self, bone_rotations: Tensor, root_position: Tensor | None = None) -> Tensor:
        """LBS with the mesh's own rig.

        Args:
            bone_rotations: ``(*, Bn, 3, 3)`` *global* rotation of each bone relative to its
                rest orientation (identity everywhere = rest pose), bones in ``bone_names`` order.
            root_position: ``(*, 3)`` world position of the root bone's head (default: rest).

        Returns:
            ``(*, V, 3)`` posed vertices: ``x' = Σ_b w_b (R_b (x − h_b) + p_b)`` with bone heads
            ``p_b = p_parent + R_parent (h_b − h_parent)``.
        """
        if bone_rotations.shape[-3:] != (self.num_bones, 3, 3):
            raise ValueError(f"bone_rotations: expected shape (*, {self.num_bones}, 3, 3), got "
                             f"{tuple(bone_rotations.shape)}")
        R = bone_rotations
        dtype = R.dtype
        heads = self.bone_heads.to(dtype)
        batch = R.shape[:-3]
        root = heads[0].expand(*batch, 3) if root_position is None else root_position.to(dtype)
        pos: list[Tensor] = []
        for b, p in enumerate(self.bone_parents):
            if p < 0:
                pos.append(root.expand(*batch, 3))
            else:
                pos.append(pos[p] + (R[..., p, :, :] @ (heads[b] - heads[p])[:, None])[..., 0])
        P = torch.stack(pos, -2)  # (*, Bn, 3)
        t = P - (R @ heads[:, :, None])[..., 0]
        return linear_blend_skinning(self.vertices, self.weights, R, t)

    # ------------------------------------------------------------------ skeleton-driven
    def bind(self, skeleton: nn.Module, bone_map: dict[str, str] | None = None,
             segments: dict[str, tuple[str, str | None, str | None]] | None = None
             ) -> SkeletonBinding:
        """Rest alignment of the mesh to a skeleton (default tables: human31).

        Raises:
            ValueError: naming ``skeleton`` if it lacks a joint the tables refer to.
        """
        bone_map = HUMAN31_BONE_MAP if bone_map is None else bone_map
        segments = HUMAN31_SEGMENTS if segments is None else segments
        names = list(skeleton.joint_names)
        needed = set(bone_map.values()) | {s[2] for s in segments.values() if s[2]} | \
            {_STATURE[1]} | {a for _, a in _STATURE[2]}
        missing = sorted(n for n in needed if n not in names)
        if missing:
            raise ValueError(f"skeleton: joints {missing} needed to drive the mesh are missing "
                             f"(has {names}); pass bone_map/segments for other skeletons")
        unknown = sorted(set(bone_map) - set(self.bone_names))
        if unknown or set(bone_map.values()) - set(segments):
            raise ValueError(f"bone_map: unknown mesh bones {unknown} or joints without a segment")
        dt = torch.float64
        rest = skeleton.joint_positions(skeleton.zero_pose(dtype=dt)).to("cpu")
        s = lambda n: rest[names.index(n)]
        m = lambda n: self.joint_centre(n).to("cpu", dt)
        top_m, top_s, ankles = _STATURE
        mesh_h = m(top_m)[2] - torch.stack([m(a)[2] for a, _ in ankles]).mean()
        skel_h = s(top_s)[2] - torch.stack([s(b)[2] for _, b in ankles]).mean()
        k = float(skel_h / mesh_h)
        joints = sorted(set(bone_map.values()), key=names.index)
        lin, org = [], []
        eye = torch.eye(3, dtype=dt)
        for j in joints:
            cube, mesh_end, skel_end = segments[j]
            if mesh_end is None:
                lin.append(k * eye)
            else:
                dm, ds = m(mesh_end) - m(cube), s(skel_end) - s(j)
                lm, ls = dm.norm(), ds.norm()
                u = dm / lm
                S = k * (eye - torch.outer(u, u)) + (ls / lm) * torch.outer(u, u)
                lin.append(rotation_between(u, ds / ls) @ S)
            org.append(m(cube))
        onehot = torch.zeros(self.num_bones, len(joints), dtype=self.weights.dtype)
        for b, name in enumerate(self.bone_names):
            if name in bone_map:
                onehot[b, joints.index(bone_map[name])] = 1.0
        if bool((onehot.sum(1) == 0).any()):
            unmapped = [n for n in self.bone_names if n not in bone_map]
            raise ValueError(f"bone_map: mesh bones {unmapped} are not mapped to a joint")
        dev = self.vertices.device
        return SkeletonBinding(torch.tensor([names.index(j) for j in joints], device=dev),
                               torch.stack(lin).to(dev), torch.stack(org).to(dev),
                               (self.weights @ onehot.to(dev)), k)

    def _binding(self, skeleton: nn.Module) -> SkeletonBinding:
        key = id(skeleton)
        cached = self._bindings.get(key)
        if cached is None or cached[0] is not skeleton or \
                cached[1].weights.device != self.vertices.device or \
                not torch.equal(cached[2], skeleton.offsets.detach().cpu()):
            cached = (skeleton, self.bind(skeleton), skeleton.offsets.detach().cpu().clone())
            self._bindings[key] = cached
        return cached[1]

    def pose_kinematics(self, kin: Any, binding: SkeletonBinding) -> Tensor:
        """Posed vertices ``(*, V, 3)`` from a skeleton's ``Kinematics`` and a binding."""
        R = kin.rotations[..., binding.joint_index, :, :]
        p = kin.positions[..., binding.joint_index, :]
        dtype = R.dtype
        lin = R @ binding.linear.to(dtype)  # (*, Jm, 3, 3)
        t = p - (lin @ binding.mesh_origin.to(dtype)[:, :, None])[..., 0]
        return linear_blend_skinning(self.vertices, binding.weights, lin, t)

    def pose_from_skeleton(self, skeleton: nn.Module, theta: Tensor,
                           offsets: Tensor | None = None) -> Tensor:
        """Mesh vertices ``(*, V, 3)`` for skeleton poses ``theta (*, D)`` (human31 by default).

        The rest alignment is computed once per skeleton (and recomputed if its offsets change);
        ``offsets`` (per-particle bone geometry) moves the joints but keeps that alignment.
        """
        kin = skeleton(theta) if offsets is None else skeleton(theta, offsets=offsets)
        return self.pose_kinematics(kin, self._binding(skeleton))

    # ------------------------------------------------------------------ export
    def to_trimesh(self, vertices: Tensor | None = None):
        """A ``trimesh.Trimesh`` of one posed mesh ``(V, 3)`` (rest mesh by default)."""
        import trimesh

        v = self.vertices if vertices is None else vertices
        if v.shape != self.vertices.shape:
            raise ValueError(f"vertices: expected one mesh {tuple(self.vertices.shape)}, got "
                             f"{tuple(v.shape)}")
        return trimesh.Trimesh(v.detach().cpu().double().numpy(), self.faces.cpu().numpy(),
                               process=False)

    def export(self, path: str | Path, vertices: Tensor | None = None) -> Path:
        """Write a posed mesh to ``.obj``/``.glb``/``.ply``/``.stl``."""
        from torchmocap.body.capsules import export_mesh

        return export_mesh(self.to_trimesh(vertices), path)

    def extra_repr(self) -> str:
        return f"num_vertices={self.num_vertices}, faces={self.faces.shape[0]}, " \
               f"bones={self.num_bones}"
