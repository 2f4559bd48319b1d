"""Batched product-of-exponentials forward kinematics for articulated skeletons.

A :class:`Skeleton` is a tree of named joints. Each joint carries an ordered list of 0-3 revolute
axes (unit vectors in its parent's frame, which at rest is aligned with the world) and a rest
offset from its parent joint. The root also has 3 translational DoF (unless disabled).

Forward kinematics, for ``theta (..., D)``::

    L_j = rot(a_1, t_1) @ rot(a_2, t_2) @ rot(a_3, t_3)      # local rotation of joint j
    R_j = R_parent(j) @ L_j                                    # global frame of joint j
    p_j = p_parent(j) + R_parent(j) @ offset_j                 # global position of joint j

Implementation notes (speed): joints without DoF are folded into the offsets of their
articulated descendants, so the number of sequential composition steps equals the depth of the
*articulated* tree (4 for ``human31``); all per-axis rotations are evaluated in one vectorised
Rodrigues step from precomputed axis algebra (``K``, ``K^2``); the batch is processed joint-major
``(J, B, 3, 3)`` so every gather is a contiguous block. No Python loop runs over particles.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchmocap.geometry.rotations import axis_angle_rotation, hat

__all__ = ["Skeleton", "Kinematics", "SkeletonError"]


class SkeletonError(ValueError):
    """A skeleton definition is malformed (cycle, missing parent, zero-length axis, ...)."""


@dataclass
class Kinematics:
    """Result of forward kinematics.

    Attributes:
        rotations: ``(..., J, 3, 3)`` global orientation of each joint's frame (the orientation of
            the bone that starts at that joint).
        positions: ``(..., J, 3)`` global joint positions in metres.
        joint_names: the skeleton's joint names, in order.
    """

    rotations: torch.Tensor
    positions: torch.Tensor
    joint_names: Sequence[str]

    @property
    def transforms(self) -> torch.Tensor:
        """Homogeneous global transforms ``(..., J, 4, 4)``."""
        R, p = self.rotations, self.positions
        top = torch.cat([R, p[..., None]], dim=-1)
        bottom = torch.zeros(*R.shape[:-2], 1, 4, dtype=R.dtype, device=R.device)
        bottom[..., 0, 3] = 1
        return torch.cat([top, bottom], dim=-2)

    def joint(self, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """``(rotation (..., 3, 3), position (..., 3))`` of one joint by name."""
        try:
            i = list(self.joint_names).index(name)
        except ValueError:
            raise KeyError(f"unknown joint {name!r}; known: {list(self.joint_names)}") from None
        return self.rotations[..., i, :, :], self.positions[..., i, :]


def _as_axis_list(axes: Any, joint: str) -> list[list[float]]:
    if axes is None:
        return []
    out = []
    for a in axes:
        a = [float(v) for v in a]
        if len(a) != 3:
            raise SkeletonError(f"joint {joint!r}: each axis needs 3 components, got {a}")
        n = math.sqrt(sum(v * v for v in a))
        if not math.isfinite(n) or n < 1e-9:
            raise SkeletonError(f"joint {joint!r}: zero-length or non-finite axis {a}")
        out.append([v / n for v in a])
    if len(out) > 3:
        raise SkeletonError(f"joint {joint!r}: at most 3 revolute axes, got {len(out)}")
    return out


class Skeleton(nn.Module):
    """Articulated skeleton with batched, differentiable forward kinematics.

    Build it with :meth:`from_dict` / :meth:`from_yaml` (see ``docs/skeleton_api.md``) or a
    preset (:func:`torchmocap.skeleton.human31`).

    Example:
        >>> from torchmocap.skeleton import human31
        >>> sk = human31()
        >>> sk(torch.zeros(200, sk.num_dofs)).positions.shape
        torch.Size([200, 21, 3])
    """

    def __init__(self, spec: Mapping[str, Any]):
        super().__init__()
        spec = copy.deepcopy(dict(spec))
        self._spec = spec
        self.name = str(spec.get("name", "skeleton"))
        joints = spec.get("joints")
        if not isinstance(joints, (list, tuple)) or not joints:
            raise SkeletonError("skeleton dict needs a non-empty 'joints' list")
        names: list[str] = []
        for j in joints:
            if not isinstance(j, Mapping) or "name" not in j:
                raise SkeletonError(f"every joint needs a 'name', got {j!r}")
            if j["name"] in names:
                raise SkeletonError(f"duplicate joint name {j['name']!r}")
            names.append(str(j["name"]))
        by_name = {str(j["name"]): j for j in joints}
        roots = [n for n in names if by_name[n].get("parent") is None]
        if len(roots) != 1:
            raise SkeletonError(f"expected exactly one root joint (parent: null), got {roots}")
        for n in names:
            p = by_name[n].get("parent")
            if p is not None and p not in by_name:
                raise SkeletonError(f"joint {n!r}: parent {p!r} is not a joint of this skeleton")
        # topological order (parents first), detecting cycles
        order: list[str] = []
        children: dict[str, list[str]] = {n: [] for n in names}
        for n in names:
            p = by_name[n].get("parent")
            if p is not None:
                children[p].append(n)
        stack = [roots[0]]
        while stack:
            n = stack.pop(0)
            order.append(n)
            stack[0:0] = children[n]
        if len(order) != len(names):
            missing = sorted(set(names) - set(order))
            raise SkeletonError(f"joints {missing} are not connected to the root (cycle?)")
        self.joint_names: list[str] = order
        self._index = {n: i for i, n in enumerate(order)}
        self.parents: list[int] = [
            -1 if by_name[n].get("parent") is None else self._index[by_name[n]["parent"]]
            for n in order
        ]
        self.root_translation = bool(by_name[roots[0]].get("translation", True))

        offsets, axes, limits, dof_names, dof_joint = [], [], [], [], []
        self.joint_axes: list[list[list[float]]] = []
        self._joint_dofs: list[list[int]] = []
        for ji, n in enumerate(order):
            j = by_name[n]
            off = [float(v) for v in j.get("offset", [0.0, 0.0, 0.0])]
            if len(off) != 3 or not all(math.isfinite(v) for v in off):
                raise SkeletonError(f"joint {n!r}: offset must be 3 finite numbers, got {off}")
            offsets.append(off)
            ax = _as_axis_list(j.get("axes"), n)
            self.joint_axes.append(ax)
            lim = j.get("limits")
            if lim is None and "limits_deg" in j:
                lim = [[math.radians(a), math.radians(b)] for a, b in j["limits_deg"]]
            if lim is None:
                lim = [[-math.inf, math.inf]] * len(ax)
            if len(lim) != len(ax):
                raise SkeletonError(f"joint {n!r}: {len(ax)} axes but {len(lim)} limit pairs")
            for lo, hi in lim:
                if not float(lo) <= float(hi):
                    raise SkeletonError(f"joint {n!r}: limit lower {lo} > upper {hi}")
            anames = j.get("dof_names") or [str(k) for k in range(len(ax))]
            if len(anames) != len(ax):
                raise SkeletonError(f"joint {n!r}: {len(ax)} axes but {len(anames)} dof_names")
            dofs = []
            if ji == 0 and self.root_translation:
                for c in "xyz":
                    dofs.append(len(dof_names))
                    dof_names.append(f"{n}_t{c}")
                    limits.append([-math.inf, math.inf])
                    dof_joint.append(ji)
            self._trans_dofs = list(range(3)) if self.root_translation else []
            for a, (lo, hi), an in zip(ax, lim, anames):
                dofs.append(len(dof_names))
                dof_names.append(f"{n}_{an}")
                limits.append([float(lo), float(hi)])
                axes.append(a)
                dof_joint.append(ji)
            self._joint_dofs.append(dofs)
        self.dof_names: list[str] = dof_names
        self._dof_index = {d: i for i, d in enumerate(dof_names)}
        self.num_dofs = len(dof_names)
        self.num_joints = len(order)

        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.float32))
        lim_t = torch.tensor(limits, dtype=torch.float32).reshape(-1, 2)
        self.register_buffer("lower", lim_t[:, 0].contiguous())
        self.register_buffer("upper", lim_t[:, 1].contiguous())
        self._build_plan(axes)

    def _apply(self, fn, recurse: bool = True):
        out = super()._apply(fn, recurse)
        if self._K.dtype == torch.float64 and self._K.numel():
            K = hat(self._axes64.to(self._K.device))
            self._K, self._K2 = K.contiguous(), (K @ K).contiguous()
        return out

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_dict(cls, spec: Mapping[str, Any]) -> Skeleton:
        """Build from a dict ``{"name": ..., "joints": [{name, parent, offset, axes, ...}]}``."""
        if not isinstance(spec, Mapping):
            raise SkeletonError(f"skeleton spec must be a mapping, got {type(spec).__name__}")
        return cls(spec)

    @classmethod
    def from_yaml(cls, path: str | Path) -> Skeleton:
        """Build from a YAML file with the :meth:`from_dict` layout."""
        import yaml

        with open(path, encoding="utf-8") as f:
            spec = yaml.safe_load(f)
        return cls.from_dict(spec)

    def to_dict(self) -> dict[str, Any]:
        """The skeleton as a plain dict (current offsets and limits), loadable by from_dict."""
        spec = copy.deepcopy(self._spec)
        by_name = {j["name"]: j for j in spec["joints"]}
        off = self.offsets.detach().cpu().double().tolist()
        lo, hi = self.lower.tolist(), self.upper.tolist()
        for ji, n in enumerate(self.joint_names):
            j = by_name[n]
            j["offset"] = off[ji]
            rot = [d for d in self._joint_dofs[ji] if d not in self._trans_dofs]
            j.pop("limits_deg", None)
            if rot:
                j["limits"] = [[lo[d], hi[d]] for d in rot]
        spec["joints"] = [by_name[n] for n in self.joint_names]
        return spec

    def _build_plan(self, axes: list[list[float]]) -> None:
        """Precompute the axis algebra and the level schedule of the articulated tree."""
        J = self.num_joints
        rot_dofs = [d for d in range(self.num_dofs) if d not in self._trans_dofs]
        self._rot_dofs = rot_dofs
        # the axes in float64 (kept off the module's buffers): a float64 copy of the skeleton
        # rebuilds its axis algebra from them instead of upcasting float32 roundings
        self._axes64 = torch.tensor(axes, dtype=torch.float64).reshape(-1, 3)
        ax = self._axes64.float()
        K = hat(ax) if len(axes) else torch.zeros(0, 3, 3)
        self.register_buffer("_K", K.contiguous(), persistent=False)
        self.register_buffer("_K2", (K @ K).contiguous(), persistent=False)
        self.register_buffer("_rot_dof_index", torch.tensor(rot_dofs, dtype=torch.long),
                             persistent=False)

        articulated = [0] + [j for j in range(1, J) if self.joint_axes[j]]
        art_pos = {j: k for k, j in enumerate(articulated)}
        # nearest articulated ancestor and the joints on the path (offset folding)
        anc, path = [], []
        for j in range(J):
            if j == 0:
                anc.append(-1)
                path.append([0])
                continue
            p, chain = self.parents[j], [j]
            while p != 0 and not self.joint_axes[p]:
                chain.append(p)
                p = self.parents[p]
            anc.append(p)
            path.append(chain)
        fold = torch.zeros(J, J)
        for j in range(J):
            for c in path[j]:
                fold[j, c] = 1.0
        self.register_buffer("_fold", fold, persistent=False)

        # local rotation groups: by number of axes, rotation-dof slots per joint
        self._local_groups = []  # (art positions, [slot index tensors])
        rot_pos = {d: k for k, d in enumerate(rot_dofs)}
        for n in (1, 2, 3):
            js = [j for j in articulated if len(self.joint_axes[j]) == n]
            if not js:
                continue
            slots = [torch.tensor([rot_pos[self._joint_dofs[j][len(self._joint_dofs[j]) - n + s]]
                                   for j in js]) for s in range(n)]
            self._local_groups.append(([art_pos[j] for j in js], slots))
        self._art_no_axes = [art_pos[j] for j in articulated if not self.joint_axes[j]]

        # levels of the articulated tree
        depth = {0: 0}
        for j in articulated[1:]:
            depth[j] = depth[anc[j]] + 1
        levels = []
        for d in range(1, max(depth.values()) + 1 if len(depth) > 1 else 1):
            js = [j for j in articulated if depth[j] == d]
            levels.append((js, [anc[j] for j in js]))
        self._articulated = articulated
        self._levels = levels
        self._leaves = [j for j in range(1, J) if not self.joint_axes[j]]
        self._leaf_anc = [anc[j] for j in self._leaves]

    def _program(self, device: torch.device) -> dict:
        """Index tensors of the FK schedule, cached per device."""
        key = str(device)
        cache = self.__dict__.setdefault("_programs", {})
        if key in cache:
            return cache[key]
        comp = [0] + [j for js, _ in self._levels for j in js] + list(self._leaves)
        where = {j: k for k, j in enumerate(comp)}
        art_order = [j for j in comp if j == 0 or self.joint_axes[j]]
        art_pos = {j: k for k, j in enumerate(self._articulated)}
        produced = []  # articulated positions in the order the groups produce them
        groups = []
        for art_ids, slots in self._local_groups:
            rot_index = self._rot_dof_index.to(device)
            groups.append([(rot_index[sl.to(device)], self._K[sl][:, None].to(device),
                            self._K2[sl][:, None].to(device)) for sl in slots])
            produced.extend(art_ids)
        produced.extend(self._art_no_axes)
        pos_in_produced = {a: k for k, a in enumerate(produced)}
        local_perm = [pos_in_produced[art_pos[j]] for j in art_order]
        levels, s0 = [], 1
        for js, parents in self._levels:
            s1 = s0 + len(js)
            levels.append(((s0, s1), torch.tensor([where[q] for q in parents], device=device)))
            s0 = s1
        leaves = None
        if self._leaves:
            leaves = ((s0, s0 + len(self._leaves)),
                      torch.tensor([where[a] for a in self._leaf_anc], device=device))
        perm = torch.tensor([where[j] for j in range(self.num_joints)], device=device)
        cache[key] = {
            "groups": groups,
            "n_no_axes": len(self._art_no_axes),
            "local_perm": torch.tensor(local_perm, device=device),
            "comp_order": torch.tensor(comp, device=device),
            "levels": levels,
            "leaves": leaves,
            "perm": perm,
        }
        return cache[key]

    # ------------------------------------------------------------------ lookups
    def joint_index(self, name: str) -> int:
        """Index of joint ``name`` (``KeyError`` listing the known joints otherwise)."""
        try:
            return self._index[name]
        except KeyError:
            raise KeyError(f"unknown joint {name!r}; known joints: {self.joint_names}") from None

    def dof_index(self, name: str) -> int:
        """Index into ``theta`` of DoF ``name`` (e.g. ``"l_knee_flex"``)."""
        try:
            return self._dof_index[name]
        except KeyError:
            raise KeyError(f"unknown DoF {name!r}; known DoFs: {self.dof_names}") from None

    def joint_dofs(self, name: str) -> list[int]:
        """``theta`` indices of joint ``name`` (root: translation first, then rotation)."""
        return list(self._joint_dofs[self.joint_index(name)])

    @property
    def rotation_dofs(self) -> list[int]:
        """Indices of all revolute DoFs."""
        return list(self._rot_dofs)

    @property
    def translation_dofs(self) -> list[int]:
        """Indices of the root's translational DoFs (empty when disabled)."""
        return list(self._trans_dofs)

    def rotation_mask(self) -> torch.Tensor:
        """``(D,)`` bool, True for the DoFs that are angles (every DoF but the root
        translation), on the skeleton's device."""
        mask = torch.ones(self.num_dofs, dtype=torch.bool, device=self.offsets.device)
        mask[self.translation_dofs] = False
        return mask

    def child_joints(self, name: str) -> list[str]:
        """Names of the direct children of joint ``name``."""
        i = self.joint_index(name)
        return [self.joint_names[c] for c, p in enumerate(self.parents) if p == i]

    def zero_pose(self, batch_shape: tuple[int, ...] = (), dtype=None, device=None):
        """``theta`` of the rest pose, ``(*batch_shape, D)``."""
        return torch.zeros(*batch_shape, self.num_dofs, dtype=dtype or self.offsets.dtype,
                           device=device or self.offsets.device)

    # ------------------------------------------------------------------ limits
    def clamp(self, theta: torch.Tensor) -> torch.Tensor:
        """Clamp ``theta (..., D)`` into the joint limits."""
        self._check_theta(theta)
        lo = self.lower.to(theta.dtype)
        hi = self.upper.to(theta.dtype)
        return torch.maximum(torch.minimum(theta, hi), lo)

    def within_limits(self, theta: torch.Tensor, tol: float = 0.0) -> torch.Tensor:
        """Boolean ``(...)``: every DoF of ``theta (..., D)`` lies inside its limits (± tol)."""
        self._check_theta(theta)
        lo = self.lower.to(theta.dtype) - tol
        hi = self.upper.to(theta.dtype) + tol
        return ((theta >= lo) & (theta <= hi)).all(-1)

    # ------------------------------------------------------------------ bone lengths
    def bone_lengths(self) -> dict[str, float]:
        """Length of the offset from each non-root joint to its parent, by child joint name."""
        n = self.offsets.norm(dim=-1).tolist()
        return {self.joint_names[j]: n[j] for j in range(1, self.num_joints)}

    def with_bone_lengths(self, lengths: Mapping[str, float] | None = None,
                          scale: float | None = None) -> Skeleton:
        """Copy with rescaled offsets: ``lengths[name]`` is the new distance from joint ``name``
        to its parent; ``scale`` multiplies every offset (applied first)."""
        spec = self.to_dict()
        by_name = {j["name"]: j for j in spec["joints"]}
        if scale is not None:
            if not (math.isfinite(scale) and scale > 0):
                raise ValueError(f"scale: expected a positive finite number, got {scale}")
            for j in spec["joints"]:
                j["offset"] = [v * scale for v in j["offset"]]
        for name, L in (lengths or {}).items():
            if name not in by_name:
                raise KeyError(f"unknown joint {name!r}; known joints: {self.joint_names}")
            if by_name[name].get("parent") is None:
                raise ValueError(f"lengths: {name!r} is the root and has no bone to its parent")
            L = float(L)
            if not (math.isfinite(L) and L >= 0):
                raise ValueError(f"lengths[{name!r}]: expected a finite length >= 0, got {L}")
            off = by_name[name]["offset"]
            n = math.sqrt(sum(v * v for v in off))
            if n < 1e-12:
                raise ValueError(f"lengths[{name!r}]: rest offset has zero length, no direction")
            by_name[name]["offset"] = [v * L / n for v in off]
        return Skeleton.from_dict(spec).to(device=self.offsets.device, dtype=self.offsets.dtype)

    # ------------------------------------------------------------------ kinematics
    def _check_theta(self, theta: torch.Tensor) -> None:
        if not isinstance(theta, torch.Tensor):
            raise TypeError(f"theta: expected a torch.Tensor, got {type(theta).__name__}")
        if theta.dim() < 1 or theta.shape[-1] != self.num_dofs:
            raise ValueError(
                f"theta: expected shape (..., {self.num_dofs}) for skeleton {self.name!r} "
                f"({self.num_dofs} DoF), got {tuple(theta.shape)}"
            )

    def forward(self, theta: torch.Tensor, offsets: torch.Tensor | None = None,
                check_finite: bool = True) -> Kinematics:
        """Forward kinematics.

        Args:
            theta: ``(..., D)`` joint parameters (root translation first, radians otherwise).
            offsets: optional ``(..., J, 3)`` per-sample rest offsets replacing ``self.offsets``
                (broadcast against the batch); gradients flow into it.
            check_finite: raise on NaN/inf in ``theta`` (one reduction; disable in hot loops
                whose inputs are known finite).
        Returns:
            :class:`Kinematics` with ``rotations (..., J, 3, 3)`` and ``positions (..., J, 3)``.
        """
        self._check_theta(theta)
        if check_finite and not bool(torch.isfinite(theta).all()):
            raise ValueError("theta: expected finite values, found NaN or inf")
        batch = theta.shape[:-1]
        dtype, device = theta.dtype, theta.device
        B = int(math.prod(batch))
        th = theta.reshape(B, self.num_dofs).transpose(0, 1)  # (D, B)
        J = self.num_joints

        if offsets is None:
            off = (self._fold.to(dtype) @ self.offsets.to(dtype))[:, None, :].expand(J, B, 3)
        else:
            if offsets.shape[-2:] != (J, 3):
                raise ValueError(
                    f"offsets: expected shape (..., {J}, 3), got {tuple(offsets.shape)}"
                )
            o = offsets.to(dtype).expand(*batch, J, 3).reshape(B, J, 3)
            off = torch.einsum("jk,bkc->jbc", self._fold.to(dtype), o)  # (J, B, 3)

        # per-axis rotations: R_d = I + sin K_d + (1 - cos) K_d^2       (Dr, B, 3, 3)
        # per-axis rotations R = I + sin K + (1 - cos) K^2, evaluated slot by slot so that every
        # gather is of angles (small), never of rotation matrices (whose index backward would
        # allocate and fill a full-size zero tensor per gather)
        prog = self._program(device)
        eye = torch.eye(3, dtype=dtype, device=device)
        local_parts = []
        for slots in prog["groups"]:
            L = None
            for dof_idx, K, K2 in slots:
                ang = th.index_select(0, dof_idx)
                R = torch.addcmul(torch.addcmul(eye, torch.sin(ang)[..., None, None],
                                                K.to(dtype)), (1 - torch.cos(ang))[..., None, None],
                                  K2.to(dtype))
                L = R if L is None else L @ R
            local_parts.append(L)
        if prog["n_no_axes"]:
            local_parts.append(eye.expand(prog["n_no_axes"], B, 3, 3))
        local = torch.cat(local_parts, 0).index_select(0, prog["local_perm"])
        off = off.index_select(0, prog["comp_order"])  # offsets in computation order

        R_buf = torch.empty(J, B, 3, 3, dtype=dtype, device=device)
        p_buf = torch.empty(J, B, 3, dtype=dtype, device=device)
        R_buf[0] = local[0]
        p_root = off[0]
        if self.root_translation:
            p_root = p_root + th[: 3].transpose(0, 1)
        p_buf[0] = p_root
        for (s0, s1), pidx in prog["levels"]:
            Rp = R_buf.index_select(0, pidx)
            p_buf[s0:s1] = p_buf.index_select(0, pidx) + (Rp @ off[s0:s1, ..., None])[..., 0]
            R_buf[s0:s1] = Rp @ local[s0:s1]
        if prog["leaves"] is not None:
            (s0, s1), aidx = prog["leaves"]
            Ra = R_buf.index_select(0, aidx)
            p_buf[s0:s1] = p_buf.index_select(0, aidx) + (Ra @ off[s0:s1, ..., None])[..., 0]
            R_buf[s0:s1] = Ra
        perm = prog["perm"]
        R_out = R_buf.index_select(0, perm).transpose(0, 1).reshape(*batch, J, 3, 3)
        p_out = p_buf.index_select(0, perm).transpose(0, 1).reshape(*batch, J, 3)
        return Kinematics(rotations=R_out, positions=p_out, joint_names=self.joint_names)

    def jacobian(self, theta: torch.Tensor, offsets: torch.Tensor | None = None):
        """Analytic geometric Jacobians of every joint w.r.t. ``theta``.

        Returns ``(kin, J_pos, J_rot)`` with ``J_pos (..., J, 3, D)`` = d p_i / d theta and
        ``J_rot (..., J, 3, D)`` = the world-frame angular velocity of frame i per unit theta
        (``dR_i = hat(J_rot dtheta) R_i``). A revolute DoF with world axis ``w`` at joint ``j``
        contributes ``w x (p_i - p_j)`` to strict descendants' positions and ``w`` to the
        rotations of ``j`` and its descendants; root translations contribute unit columns.
        """
        kin = self.forward(theta, offsets)
        batch = theta.shape[:-1]
        dtype, device = theta.dtype, theta.device
        D, Jn = self.num_dofs, self.num_joints
        R, p = kin.rotations, kin.positions
        plan = self._jacobian_plan(device)
        # the DoFs are the root's translations, then every rotation in joint order: the
        # rotation columns below are one run, written whole, so only the translations' need zeros
        Jp = torch.empty(*batch, Jn, 3, D, dtype=dtype, device=device)
        Jr = torch.empty(*batch, Jn, 3, D, dtype=dtype, device=device)
        if self._trans_dofs:
            Jp[..., self._trans_dofs] = 0.0
            Jr[..., self._trans_dofs] = 0.0
        for d in self._trans_dofs:
            Jp[..., :, d % 3, d] = 1.0
        if plan is None:  # no rotation DoF
            return kin, Jp, Jr
        Dr = plan["cols"].numel()
        axes = plan["axes"].to(dtype)  # (Dr, 3)
        rot = axis_angle_rotation(axes.expand(*batch, Dr, 3), theta[..., plan["cols"]])
        # the frame each axis turns in: its parent's rotation times the joint's earlier axes
        eye = torch.eye(3, dtype=dtype, device=device).expand(*batch, 1, 3, 3)
        pre = torch.cat([eye, R], -3).index_select(-3, plan["parent"])  # (..., Dr, 3, 3)
        for lvl, prv in plan["levels"]:
            pre = pre.index_copy(-3, lvl, pre.index_select(-3, prv) @ rot.index_select(-3, prv))
        w = (pre @ axes[..., None])[..., 0]  # (..., Dr, 3) world axes
        wt = w.transpose(-1, -2)[..., None, :, :]  # (..., 1, 3, Dr)
        # w_d x (p_i - p_j(d)) for every joint i and DoF d: one product p @ hat(w) (laid out
        # (c, a, d)), minus w_d x p_j(d); kept on the strict descendants of j(d)
        hat_w = hat(w).transpose(-1, -3).reshape(*batch, 3, 3 * Dr)
        lin = (p @ hat_w).view(*batch, Jn, 3, Dr)
        own = torch.cross(w, p.index_select(-2, plan["joint"]), dim=-1)  # (..., Dr, 3)
        lin = lin - own.transpose(-1, -2)[..., None, :, :]
        span, strict, incl = plan["span"], plan["strict"].to(dtype), plan["incl"].to(dtype)
        if torch.is_grad_enabled() and (lin.requires_grad or wt.requires_grad):
            Jp[..., span] = lin * strict  # differentiable (second-order fits)
            Jr[..., span] = wt * incl
        else:  # straight into the output, no temporaries
            torch.mul(lin, strict, out=Jp[..., span])
            torch.mul(wt, incl, out=Jr[..., span])
        return kin, Jp, Jr

    def _jacobian_plan(self, device) -> dict | None:
        """Index tensors of :meth:`jacobian` per device: for every rotation DoF (in joint order)
        its column, joint, parent (+1; 0 = the world), unit axis, the joints whose rotation
        (``incl``, ``(J, 1, Dr)``) and position (``strict``) it moves, and the DoFs grouped by
        their place within their joint (``levels``: ``(positions, previous DoF's positions)``)."""
        cache = self.__dict__.setdefault("_jac_plans", {})
        key = str(device)
        if key not in cache:
            sub = self._subtree_masks()
            cols, joint, parent, axes, place = [], [], [], [], []
            for j in range(self.num_joints):
                dofs = [d for d in self._joint_dofs[j] if d not in self._trans_dofs]
                for k, (a, d) in enumerate(zip(self.joint_axes[j], dofs)):
                    cols.append(d)
                    joint.append(j)
                    parent.append(self.parents[j] + 1)
                    axes.append([float(v) for v in a])
                    place.append(k)
            if not cols:
                cache[key] = None
                return None
            Dr = len(cols)
            incl = torch.zeros(self.num_joints, 1, Dr, dtype=torch.bool)
            strict = torch.zeros(self.num_joints, 1, Dr, dtype=torch.bool)
            for r, j in enumerate(joint):
                strict[sub[j][0], 0, r] = True
                incl[sub[j][1], 0, r] = True
            if cols != list(range(len(self._trans_dofs), self.num_dofs)):
                raise RuntimeError("jacobian: expected the rotation DoFs after the root's "
                                   f"translations, in joint order; got columns {cols}")
            levels = []
            for k in range(1, max(place) + 1):
                at = [r for r in range(Dr) if place[r] == k]
                levels.append((torch.tensor(at, device=device),
                               torch.tensor([r - 1 for r in at], device=device)))
            cache[key] = {"cols": torch.tensor(cols, device=device),
                          "joint": torch.tensor(joint, device=device),
                          "parent": torch.tensor(parent, device=device),
                          "axes": torch.tensor(axes, dtype=torch.float64, device=device),
                          "incl": incl.to(device), "strict": strict.to(device),
                          "levels": levels, "span": slice(cols[0], cols[0] + Dr)}
        return cache[key]

    def _subtree_masks(self):
        if getattr(self, "_subtrees", None) is None:
            kids: dict[int, list[int]] = {j: [] for j in range(self.num_joints)}
            for c, q in enumerate(self.parents):
                if q >= 0:
                    kids[q].append(c)
            out = []
            for j in range(self.num_joints):
                stack, desc = list(kids[j]), []
                while stack:
                    c = stack.pop()
                    desc.append(c)
                    stack.extend(kids[c])
                desc.sort()
                out.append((desc, [j] + desc))
            self._subtrees = out
        return self._subtrees

    def joint_positions(self, theta: torch.Tensor, offsets: torch.Tensor | None = None):
        """Global joint positions ``(..., J, 3)``."""
        return self.forward(theta, offsets).positions

    def bone_rotations(self, theta: torch.Tensor, offsets: torch.Tensor | None = None):
        """Global joint-frame (bone) rotations ``(..., J, 3, 3)``."""
        return self.forward(theta, offsets).rotations

    def extra_repr(self) -> str:
        return f"name={self.name!r}, joints={self.num_joints}, dofs={self.num_dofs}"
