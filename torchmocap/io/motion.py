"""``MotionClip``: one skeleton plus per-frame local joint rotations, read from a motion file.

World frame: **Z up, metres**. BVH and ASF/AMC files are Y up; the readers convert with the fixed
rotation :data:`Y_UP_TO_Z_UP`, ``(x, y, z)_src -> (x, -z, y)``, so a person stands along +z and,
for the CMU/HDM05 files, faces roughly -y (human31's rest direction).

A clip stores local rotations ``(T, J, 3, 3)`` (the truth) and, per joint, the ordered revolute
axes its file animates (BVH channel order, ASF ``C M C^-1``). :meth:`MotionClip.to_skeleton`
turns that into a core :class:`torchmocap.skeleton.Skeleton` (one joint per source joint, its
axes = the channels' axes) and the per-frame ``theta``; positions and global rotations are
computed by that skeleton's forward kinematics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch

from torchmocap.io._euler import angles_to_matrix, matrix_to_angles

__all__ = ["MotionClip", "Y_UP_TO_Z_UP", "y_up_to_z_up"]

#: ``p_zup = Y_UP_TO_Z_UP @ p_yup``: (x, y, z) -> (x, -z, y) (a proper rotation, +90 deg about x).
Y_UP_TO_Z_UP = torch.tensor(
    [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64
)


def y_up_to_z_up(v: torch.Tensor) -> torch.Tensor:
    """Map Y-up vectors ``(*, 3)`` to the Z-up world: ``(x, y, z) -> (x, -z, y)``."""
    return torch.stack([v[..., 0], -v[..., 2], v[..., 1]], -1)


def z_up_to_y_up(v: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`y_up_to_z_up`: ``(x, y, z) -> (x, z, -y)``."""
    return torch.stack([v[..., 0], v[..., 2], -v[..., 1]], -1)


@dataclass(eq=False, repr=False)
class MotionClip:
    """A motion: skeleton geometry and per-frame local rotations (Z-up metres, radians).

    Attributes:
        joint_names: ``J`` unique names; end sites are 0-DoF leaves named ``<parent>_end``.
        parents: ``J`` parent indices, ``-1`` for the root (index 0); parents precede children.
        offsets: ``(J, 3)`` rest offset of each joint from its parent, in the parent's frame
            (at rest every frame is aligned with the world), metres.
        rotations: ``(T, J, 3, 3)`` local rotation of each joint (identity for 0-DoF joints).
        root_translation: ``(T, 3)`` added to ``offsets[0]`` to place the root, metres.
        fps: frames per second.
        axes: per joint a ``(k_j, 3)`` tensor of its ordered revolute axes, ``k_j`` in 0..3:
            ``rotations[:, j] = rot(a1, t1) @ ... @ rot(ak, tk)`` for some angles.
        local_translations: joint name -> ``(T, 3)`` per-frame offset that *replaces*
            ``offsets[j]`` (BVH joints with position channels below the root).
        source_format: ``"bvh"``, ``"asf"``, or ``"skeleton"`` (built from a core Skeleton).
        skeleton_family: name of the skeleton map the clip matches (see
            :mod:`torchmocap.io.skeleton_maps`), or ``None``.
        source_path: file the clip was read from, if any.
        unit: metres per length unit of the source file (1.0 when not read from a file).
        channels: optional per-joint BVH channel names (kept so a written BVH keeps the order).

    Example:
        >>> from torchmocap.io import bundled_clip_path, read_bvh
        >>> clip = read_bvh(bundled_clip_path())  # 4 s of CMU 131_01, 3dsMax-style BVH
        >>> clip.global_positions().shape
        torch.Size([480, 38, 3])
    """

    joint_names: list[str]
    parents: list[int]
    offsets: torch.Tensor
    rotations: torch.Tensor
    root_translation: torch.Tensor
    fps: float
    axes: list[torch.Tensor]
    local_translations: dict[str, torch.Tensor] = field(default_factory=dict)
    source_format: str = "unknown"
    skeleton_family: str | None = None
    source_path: str | None = None
    unit: float = 1.0
    channels: list[tuple[str, ...]] | None = None

    def __post_init__(self) -> None:
        J = len(self.joint_names)
        if J == 0:
            raise ValueError("MotionClip: needs at least one joint")
        if len(set(self.joint_names)) != J:
            dup = sorted({n for n in self.joint_names if self.joint_names.count(n) > 1})
            raise ValueError(f"MotionClip: duplicate joint names {dup}")
        if len(self.parents) != J or self.parents[0] != -1:
            raise ValueError("MotionClip: parents must have one entry per joint, root (-1) first")
        for j, p in enumerate(self.parents[1:], start=1):
            if not 0 <= p < j:
                raise ValueError(
                    f"MotionClip: joint {self.joint_names[j]!r} parent {p} must precede it"
                )
        if tuple(self.offsets.shape) != (J, 3):
            raise ValueError(f"offsets: expected shape ({J}, 3), got {tuple(self.offsets.shape)}")
        if self.rotations.dim() != 4 or tuple(self.rotations.shape[1:]) != (J, 3, 3):
            raise ValueError(
                f"rotations: expected shape (T, {J}, 3, 3), got {tuple(self.rotations.shape)}"
            )
        T = self.rotations.shape[0]
        if T < 1:
            raise ValueError("rotations: a clip needs at least one frame")
        if tuple(self.root_translation.shape) != (T, 3):
            raise ValueError(
                f"root_translation: expected shape ({T}, 3), "
                f"got {tuple(self.root_translation.shape)}"
            )
        if len(self.axes) != J or any(
            a.dim() != 2 or a.shape[1] != 3 or a.shape[0] > 3 for a in self.axes
        ):
            raise ValueError("axes: expected one (k, 3) tensor per joint with k <= 3")
        for name, tr in self.local_translations.items():
            if name not in self.joint_names:
                raise ValueError(f"local_translations: unknown joint {name!r}")
            if tuple(tr.shape) != (T, 3):
                raise ValueError(
                    f"local_translations[{name!r}]: expected shape ({T}, 3), got {tuple(tr.shape)}"
                )
        if isinstance(self.fps, bool) or not (
            isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0
        ):
            raise ValueError(f"fps: expected a positive finite number, got {self.fps!r}")
        for name, t in (
            ("offsets", self.offsets),
            ("rotations", self.rotations),
            ("root_translation", self.root_translation),
        ):
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name}: expected finite values, found NaN or inf")

    def __repr__(self) -> str:
        return (
            f"MotionClip(family={self.skeleton_family!r}, format={self.source_format!r}, "
            f"joints={self.num_joints}, frames={self.num_frames}, fps={self.fps:g}, "
            f"dtype={self.rotations.dtype}, source={self.source_path!r})"
        )

    # ------------------------------------------------------------------ basic properties
    @property
    def num_frames(self) -> int:
        """``T``."""
        return int(self.rotations.shape[0])

    @property
    def num_joints(self) -> int:
        """``J`` (end sites included)."""
        return len(self.joint_names)

    @property
    def duration_s(self) -> float:
        """``T / fps`` seconds."""
        return self.num_frames / float(self.fps)

    def joint_index(self, name: str) -> int:
        """Index of joint ``name`` (``KeyError`` listing the joints otherwise)."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise KeyError(f"unknown joint {name!r}; joints: {self.joint_names}") from None

    def children(self, j: int) -> list[int]:
        """Indices of the children of joint ``j``."""
        return [c for c, p in enumerate(self.parents) if p == j]

    def frame_offsets(self) -> torch.Tensor:
        """Per-frame offsets ``(T, J, 3)`` with position-channel joints' translations applied."""
        off = self.offsets.expand(self.num_frames, -1, -1).clone()
        for name, tr in self.local_translations.items():
            off[:, self.joint_index(name)] = tr
        return off

    # ------------------------------------------------------------------ skeleton / FK
    def to_skeleton(self, name: str | None = None):
        """Core skeleton and per-frame pose of this clip.

        Each source joint becomes one Skeleton joint with the same offset and the same ordered
        revolute axes (BVH ``Zrotation Xrotation Yrotation`` -> axes z, x, y of the file,
        expressed in the Z-up world); the root also gets ``tx, ty, tz``.

        Returns:
            ``(skeleton, theta)``: a :class:`torchmocap.skeleton.Skeleton` (float64 buffers when
            the clip is float64) and ``theta (T, D)``: root translation, then each joint's
            angles (radians) in joint order, reproducing :attr:`rotations` exactly.
        """
        from torchmocap.skeleton import Skeleton

        joints = []
        for j, n in enumerate(self.joint_names):
            spec = {
                "name": n,
                "parent": None if j == 0 else self.joint_names[self.parents[j]],
                "offset": [float(v) for v in self.offsets[j]],
                "axes": [[float(v) for v in a] for a in self.axes[j]],
            }
            joints.append(spec)
        sk = Skeleton.from_dict(
            {"name": name or (self.skeleton_family or "motion_clip"), "joints": joints}
        )
        sk = sk.to(dtype=self.offsets.dtype, device=self.offsets.device)
        order = [self.joint_names.index(n) for n in sk.joint_names]
        parts = [self.root_translation]
        for j in order:
            if self.axes[j].shape[0]:
                parts.append(matrix_to_angles(self.rotations[:, j], self.axes[j]))
        theta = torch.cat(parts, -1)
        return sk, theta

    def _kinematics(self):
        sk, theta = self.to_skeleton()
        order = [self.joint_names.index(n) for n in sk.joint_names]
        off = self.frame_offsets() if self.local_translations else self.offsets
        kin = sk(theta, offsets=off[..., order, :])
        inv = [sk.joint_names.index(n) for n in self.joint_names]
        return kin, inv

    def global_positions(self) -> torch.Tensor:
        """World joint positions ``(T, J, 3)`` in metres, by the core Skeleton's FK."""
        kin, inv = self._kinematics()
        return kin.positions[:, inv]

    def global_rotations(self) -> torch.Tensor:
        """World joint frames ``(T, J, 3, 3)`` (orientation of the bone starting at each joint)."""
        kin, inv = self._kinematics()
        return kin.rotations[:, inv]

    @classmethod
    def from_skeleton(
        cls, skeleton, theta: torch.Tensor, fps: float, skeleton_family: str | None = None
    ) -> MotionClip:
        """Clip of a core Skeleton driven by ``theta (T, D)`` (e.g. a human31 track, to write).

        Local rotations come from the skeleton's own FK (``L_j = R_parent^T R_j``), so any
        axis layout is carried over; the root must have translational DoF. ``skeleton_family``
        defaults to the detected one (``"human31"`` for the preset), so :func:`write_bvh` writes
        metres and reading the file back needs no ``unit``.
        """
        if theta.dim() != 2 or theta.shape[-1] != skeleton.num_dofs:
            raise ValueError(
                f"theta: expected shape (T, {skeleton.num_dofs}), got {tuple(theta.shape)}"
            )
        if not getattr(skeleton, "root_translation", True):
            raise ValueError("skeleton: the root needs translational DoF (tx, ty, tz) for a clip")
        theta = theta.detach()
        kin = skeleton(theta)
        Rg = kin.rotations
        parents = list(skeleton.parents)
        local = Rg.clone()
        for j, p in enumerate(parents):
            if p >= 0:
                local[:, j] = Rg[:, p].transpose(-1, -2) @ Rg[:, j]
        axes = [torch.tensor(a, dtype=theta.dtype).reshape(-1, 3) for a in skeleton.joint_axes]
        if skeleton_family is None:
            from torchmocap.io.skeleton_maps import detect_family

            skeleton_family = detect_family(list(skeleton.joint_names))
        return cls(
            joint_names=list(skeleton.joint_names),
            parents=parents,
            offsets=skeleton.offsets.detach().to(theta.dtype).clone(),
            rotations=local,
            root_translation=theta[:, :3].clone(),
            fps=float(fps),
            axes=axes,
            source_format="skeleton",
            skeleton_family=skeleton_family,
        )

    # ------------------------------------------------------------------ editing
    def to(self, dtype: torch.dtype | None = None, device=None) -> MotionClip:
        """Copy with every tensor cast to ``dtype`` and/or moved to ``device``."""

        def mv(t: torch.Tensor) -> torch.Tensor:
            return t.to(device=device, dtype=dtype)

        return replace(
            self,
            offsets=mv(self.offsets),
            rotations=mv(self.rotations),
            root_translation=mv(self.root_translation),
            axes=[mv(a) for a in self.axes],
            local_translations={k: mv(v) for k, v in self.local_translations.items()},
        )

    def in_place(self) -> MotionClip:
        """The clip with its root held at the first frame's position and orientation (every
        other joint's motion unchanged): a person standing in place, as in sequences where only
        the upper body is tracked (Hauberg & Pedersen 2011, §5)."""
        return replace(
            self,
            rotations=torch.cat([self.rotations[:1, :1].expand(self.num_frames, 1, 3, 3),
                                 self.rotations[:, 1:]], 1),
            root_translation=self.root_translation[:1].expand(self.num_frames, 3).clone(),
        )

    def slice(self, start: int | None = None, stop: int | None = None) -> MotionClip:
        """Frames ``start:stop`` (Python slice semantics, step 1) as a new clip."""
        idx = range(self.num_frames)[slice(start, stop)]
        if len(idx) == 0:
            raise ValueError(f"slice({start}, {stop}) of a {self.num_frames}-frame clip is empty")
        s = slice(idx.start, idx.stop)
        return replace(
            self,
            rotations=self.rotations[s].clone(),
            root_translation=self.root_translation[s].clone(),
            local_translations={k: v[s].clone() for k, v in self.local_translations.items()},
        )

    def resample(self, fps: float) -> MotionClip:
        """Resample to ``fps`` (e.g. 120 -> 25): slerp on rotations, linear on translations.

        New frame ``i`` is at time ``i / fps``; frames run while that time stays within the
        source clip (``(T - 1) / fps_src``). Joints with 1 or 2 axes are re-projected onto
        their axes by :meth:`to_skeleton` (exact for 1 axis; 2-axis slerp paths may leave the
        reachable set by a second-order amount).
        """
        from torchmocap.geometry import matrix_to_quaternion, quaternion_slerp, quaternion_to_matrix

        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps: expected a positive finite number, got {fps!r}")
        T = self.num_frames
        n_new = int(math.floor((T - 1) * fps / self.fps + 1e-9)) + 1
        dtype = self.rotations.dtype
        u = torch.arange(n_new, dtype=dtype, device=self.rotations.device) * (self.fps / fps)
        i0 = u.floor().long().clamp(0, max(T - 2, 0))
        i1 = (i0 + 1).clamp(max=T - 1)
        w = (u - i0.to(dtype)).clamp(0, 1)

        def lerp(x: torch.Tensor) -> torch.Tensor:
            ww = w.reshape(-1, *([1] * (x.dim() - 1)))
            return x[i0] * (1 - ww) + x[i1] * ww

        q = matrix_to_quaternion(self.rotations)  # (T, J, 4)
        qn = quaternion_slerp(q[i0], q[i1], w[:, None, None])
        rot = quaternion_to_matrix(qn)
        return replace(
            self,
            rotations=rot,
            root_translation=lerp(self.root_translation),
            local_translations={k: lerp(v) for k, v in self.local_translations.items()},
            fps=float(fps),
        )

    def change_basis(self, G: torch.Tensor) -> MotionClip:
        """The same motion in world axes rotated by ``G (3, 3)`` (a proper rotation): every
        joint position becomes ``G @ p`` and every bone frame ``G R G^T`` — rest offsets,
        rotation axes and translations are rotated, local rotations conjugated (what reading a
        Y-up file as Z-up does with ``G = Y_UP_TO_Z_UP``)."""
        G = torch.as_tensor(G).to(self.offsets)
        if tuple(G.shape) != (3, 3):
            raise ValueError(f"G: expected shape (3, 3), got {tuple(G.shape)}")
        eye = torch.eye(3, dtype=G.dtype, device=G.device)
        if not (torch.allclose(G @ G.T, eye, atol=1e-6) and float(torch.det(G)) > 0):
            raise ValueError("G: expected a proper rotation matrix (G G^T = I, det G = +1)")
        return replace(
            self,
            offsets=self.offsets @ G.T,
            rotations=G @ self.rotations @ G.T,
            root_translation=self.root_translation @ G.T,
            axes=[a @ G.T for a in self.axes],
            local_translations={k: v @ G.T for k, v in self.local_translations.items()},
        )

    def with_angles(self, joint: str, angles: torch.Tensor) -> MotionClip:
        """Copy where ``joint``'s local rotation is set from ``angles (T, k)`` about its axes."""
        j = self.joint_index(joint)
        rot = self.rotations.clone()
        rot[:, j] = angles_to_matrix(angles.to(rot.dtype), self.axes[j])
        return replace(self, rotations=rot)

    def path_between(self, a: int, b: int) -> list[int]:
        """Joints on the tree path from ``a`` to ``b`` (both included)."""

        def up(j: int) -> list[int]:
            chain = [j]
            while self.parents[chain[-1]] >= 0:
                chain.append(self.parents[chain[-1]])
            return chain

        ua, ub = up(a), up(b)
        common = next(x for x in ua if x in set(ub))
        return ua[: ua.index(common) + 1] + list(reversed(ub[: ub.index(common)]))
