"""Analytic inverse kinematics from orientation sensors: Pons-Moll et al. (2010), §4.1.

With ``S`` orientation sensors on bones, ``3S`` pose parameters — the *passive* ones, one 3-DoF
joint per sensor on the chain above it — are functions of the other *active* ones and the sensor
orientations. ``g(theta) = x_a`` keeps the active coordinates; ``g^{-1}(x_a, sensors) = theta``
solves, for each sensor ``s`` with passive joint ``j`` (eqs. 9–14)::

    R_pj L_j R_cj = R_TS R_SB         =>   L_j = R_pj^T (R_TS R_SB) R_cj^T

then splits ``L_j`` into the joint's three axis angles (Paden–Kahan subproblems 2 and 1, or the
closed form when the axes are mutually orthogonal, as in ``human31``). ``R_pj`` is the global
rotation of ``j``'s parent and ``R_cj`` the rotation from ``j``'s frame to the sensor bone's frame;
both come from the active parameters — and, above an upstream sensor's bone, from that bone's
requested orientation (exactly what the upstream solution achieves whenever it is reachable, always
the case for orthogonal axes). So every passive joint is solved in one batched call.

Sensor calibration (eq. 8): ``R_SB = R_TS,0^T R_TB,0`` from a frame with known pose.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import nn

from torchmocap.geometry import quaternion_to_matrix
from torchmocap.geometry.subproblems import (
    axes_are_orthogonal,
    orthogonal_three_axis_decomposition,
    three_axis_decomposition,
)

__all__ = [
    "PAPER_SENSORS",
    "SensorManifold",
    "SensorManifoldError",
    "ManifoldSolution",
    "sensor_rotations",
]

#: The paper's five tracking sensors (name -> bone): back, both forearms, both shanks.
PAPER_SENSORS: dict[str, str] = {
    "back": "pelvis",
    "l_forearm": "l_elbow",
    "r_forearm": "r_elbow",
    "l_shank": "l_knee",
    "r_shank": "r_knee",
}


class SensorManifoldError(ValueError):
    """A sensor placement or passive-joint choice that the analytic IK cannot handle."""


@dataclass
class ManifoldSolution:
    """Result of :meth:`SensorManifold.inverse`.

    Attributes:
        theta: ``(*, D)`` full poses.
        residual: ``(*, S)`` angle (radians) between the achieved and the requested sensor-bone
            orientation, or ``None`` when not computed.
        within_limits: ``(*, S)`` bool, the chosen passive angles lie inside the joint limits.
        gimbal: ``(*, S)`` bool, the passive joint is at gimbal lock (first angle taken from
            the reference pose).
    """

    theta: torch.Tensor
    residual: torch.Tensor | None
    within_limits: torch.Tensor
    gimbal: torch.Tensor


def sensor_rotations(sensors: torch.Tensor, num_sensors: int) -> torch.Tensor:
    """Validate sensor orientations and return rotation matrices ``(*, S, 3, 3)``.

    Args:
        sensors: ``(*, S, 3, 3)`` rotation matrices or ``(*, S, 4)`` unit quaternions (w, x, y, z).
        num_sensors: expected ``S``.
    """
    if not isinstance(sensors, torch.Tensor):
        raise TypeError(f"sensors: expected a torch.Tensor, got {type(sensors).__name__}")
    if sensors.dim() >= 2 and sensors.shape[-1] == 4:
        if sensors.shape[-2] != num_sensors:
            raise ValueError(f"sensors: expected {num_sensors} sensors (*, {num_sensors}, 4), "
                             f"got shape {tuple(sensors.shape)}")
        if not bool(torch.isfinite(sensors).all()):
            raise ValueError("sensors: expected finite quaternions, found NaN or inf")
        tol = 1e-6 if sensors.dtype == torch.float64 else 1e-4
        if float((sensors.norm(dim=-1) - 1).abs().max()) > tol:
            raise ValueError(f"sensors: expected unit quaternions (w, x, y, z), tolerance {tol}")
        return quaternion_to_matrix(sensors)
    if sensors.dim() >= 3 and sensors.shape[-2:] == (3, 3):
        if sensors.shape[-3] != num_sensors:
            raise ValueError(f"sensors: expected {num_sensors} sensors (*, {num_sensors}, 3, 3), "
                             f"got shape {tuple(sensors.shape)}")
        if not bool(torch.isfinite(sensors).all()):
            raise ValueError("sensors: expected finite rotation matrices, found NaN or inf")
        return sensors
    raise ValueError(f"sensors: expected (*, {num_sensors}, 3, 3) rotations or "
                     f"(*, {num_sensors}, 4) quaternions, got {tuple(sensors.shape)}")


class SensorManifold(nn.Module):
    """The sensor manifold of a skeleton: ``g`` (pose -> active coordinates) and ``g^{-1}``.

    Args:
        skeleton: a :class:`torchmocap.skeleton.Skeleton`.
        sensors: ``{sensor name: bone (joint) name}``; the sensor is rigidly attached to the bone
            that starts at that joint. Default: :data:`PAPER_SENSORS`.
        passive: optional ``{sensor name: joint name}`` choosing each sensor's passive 3-DoF
            joint. Default: the nearest joint with three rotational DoF at or above the sensor
            bone, below any upstream sensor's bone (the paper's root, hips and shoulders).

    Buffers: ``sensor_to_bone`` ``(S, 3, 3)`` calibration offsets ``R_SB`` (identity until
    :meth:`calibrate`), ``active_index`` ``(d,)`` and ``passive_index`` ``(S, 3)`` into ``theta``.

    Example:
        >>> from torchmocap.skeleton import human31
        >>> m = SensorManifold(human31())
        >>> theta = torch.zeros(200, 31)
        >>> m.inverse(m(theta), m.sensor_orientations(theta)).theta.shape
        torch.Size([200, 31])
    """

    def __init__(
        self,
        skeleton: nn.Module,
        sensors: Mapping[str, str] | None = None,
        passive: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__()
        sensors = dict(PAPER_SENSORS if sensors is None else sensors)
        if not sensors:
            raise SensorManifoldError("sensors: expected at least one sensor")
        self.skeleton = skeleton
        sk = skeleton
        names = list(sk.joint_names)
        for s, b in sensors.items():
            if b not in names:
                raise SensorManifoldError(
                    f"sensors: sensor {s!r} is on unknown bone {b!r}; known bones: {names}")
        passive = dict(passive or {})
        for s, j in passive.items():
            if s not in sensors:
                raise SensorManifoldError(f"passive: unknown sensor {s!r}")
            if j not in names:
                raise SensorManifoldError(f"passive: sensor {s!r} names unknown joint {j!r}")
        parents = sk.parents
        trans = set(sk.translation_dofs)

        def rot_dofs(j: int) -> list[int]:
            return [d for d in sk.joint_dofs(names[j]) if d not in trans]

        def chain_to_root(j: int) -> list[int]:  # [j, parent, ..., root]
            out = []
            while j >= 0:
                out.append(j)
                j = parents[j]
            return out

        # process sensors from the root outwards so upstream sensors are known
        order = sorted(sensors, key=lambda s: len(chain_to_root(names.index(sensors[s]))))
        bone_of = {s: names.index(sensors[s]) for s in order}
        bone_set = {}
        for s in order:
            if bone_of[s] in bone_set:
                raise SensorManifoldError(
                    f"sensors: {s!r} and {bone_set[bone_of[s]]!r} are on the same bone")
            bone_set[bone_of[s]] = s
        passive_of: dict[str, int] = {}
        upstream_of: dict[str, str | None] = {}
        for s in order:
            chain = chain_to_root(bone_of[s])
            # nearest upstream sensor bone strictly above this bone
            up = next((bone_set[c] for c in chain[1:] if c in bone_set), None)
            upstream_of[s] = up
            allowed = chain if up is None else chain[: chain.index(bone_of[up])]
            if s in passive:
                j = names.index(passive[s])
                if j not in allowed:
                    raise SensorManifoldError(
                        f"passive: joint {passive[s]!r} of sensor {s!r} must lie on the chain "
                        f"from bone {sensors[s]!r} up to (not including) "
                        f"{'the root' if up is None else repr(sensors[up])}")
            else:
                cand = [c for c in allowed if len(rot_dofs(c)) == 3]
                if not cand:
                    raise SensorManifoldError(
                        f"sensors: no free 3-DoF joint for sensor {s!r} between bone "
                        f"{sensors[s]!r} and {'the root' if up is None else repr(sensors[up])}")
                j = cand[0]
            if len(rot_dofs(j)) != 3:
                raise SensorManifoldError(
                    f"passive: joint {names[j]!r} of sensor {s!r} has {len(rot_dofs(j))} "
                    "rotational DoF, expected 3")
            if j in passive_of.values():
                raise SensorManifoldError(f"passive: joint {names[j]!r} is used by two sensors")
            passive_of[s] = j

        self.sensor_names: list[str] = list(sensors)  # user order = order of the S axis
        self.sensor_bones: list[str] = [sensors[s] for s in self.sensor_names]
        self.passive_joints: list[str] = [names[passive_of[s]] for s in self.sensor_names]
        self.num_sensors = S = len(self.sensor_names)
        sidx = {s: i for i, s in enumerate(self.sensor_names)}
        passive_dofs = [rot_dofs(passive_of[s]) for s in self.sensor_names]
        flat_passive = [d for ds in passive_dofs for d in ds]
        self.active_dofs: list[int] = [d for d in range(sk.num_dofs) if d not in flat_passive]
        self.num_dofs = sk.num_dofs
        self.num_active = len(self.active_dofs)
        self.active_names = [sk.dof_names[d] for d in self.active_dofs]

        # chains of active joints: above the passive joint (from the upstream bone or the root)
        # and below it (down to the sensor bone, inclusive)
        above, below, upstream = [], [], []
        for s in self.sensor_names:
            j, b, up = passive_of[s], bone_of[s], upstream_of[s]
            anc = chain_to_root(parents[j]) if parents[j] >= 0 else []
            if up is not None:
                anc = anc[: anc.index(bone_of[up])]
            above.append(list(reversed(anc)))  # root-most first
            cb = chain_to_root(b)
            below.append(list(reversed(cb[: cb.index(j)])))  # child of j ... b
            upstream.append(-1 if up is None else sidx[up])
        needed = sorted({k for ch in above + below for k in ch if rot_dofs(k)})
        self._needed_joints = needed
        npos = {k: i for i, k in enumerate(needed)}
        eye_slot = len(needed)
        la = max([len(c) for c in above] + [0])
        lb = max([len(c) for c in below] + [0])

        def pad(chains: list[list[int]], n: int) -> torch.Tensor:
            rows = [[npos[k] for k in c if k in npos] for c in chains]
            n = max([len(r) for r in rows] + [0])
            return torch.tensor([r + [eye_slot] * (n - len(r)) for r in rows],
                                dtype=torch.long).reshape(S, n)

        self.register_buffer("_above", pad(above, la), persistent=False)
        self.register_buffer("_below", pad(below, lb), persistent=False)
        self.register_buffer("_upstream", torch.tensor(upstream, dtype=torch.long),
                             persistent=False)
        self._has_upstream = any(u >= 0 for u in upstream)
        # levels for the residual computation (achieved orientations through upstream bones)
        level = []
        for i in range(S):
            d, u = 0, upstream[i]
            while u >= 0:
                d, u = d + 1, upstream[u]
            level.append(d)
        self._levels = [[i for i in range(S) if level[i] == lv] for lv in range(max(level) + 1)]

        # per-DoF axis algebra of the needed joints (slots padded to 3 with zero axes)
        axes_all = [ax for ji in range(len(names)) for ax in sk.joint_axes[ji]]
        rot_list = sk.rotation_dofs
        def axis_of(d: int) -> list[float]:
            return axes_all[rot_list.index(d)]
        nd = max([len(rot_dofs(k)) for k in needed] + [1])
        dof_idx, dof_axes = [], []
        for k in needed:
            ds = rot_dofs(k)
            dof_idx.append(ds + [ds[0]] * (nd - len(ds)))
            dof_axes.append([axis_of(d) for d in ds] + [[0.0, 0.0, 0.0]] * (nd - len(ds)))
        ax_t = torch.tensor(dof_axes, dtype=torch.float32).reshape(len(needed), nd, 3)
        ax_t = torch.nn.functional.normalize(ax_t, dim=-1)
        from torchmocap.geometry import hat

        K = hat(ax_t)
        self.register_buffer("_need_dofs", torch.tensor(dof_idx, dtype=torch.long).reshape(
            len(needed), nd), persistent=False)
        self.register_buffer("_need_K", K, persistent=False)
        self.register_buffer("_need_K2", K @ K, persistent=False)

        paxes = torch.tensor([[axis_of(d) for d in ds] for ds in passive_dofs],
                             dtype=torch.float64).reshape(S, 3, 3)
        paxes = torch.nn.functional.normalize(paxes, dim=-1)
        self._orthogonal = axes_are_orthogonal(paxes, tol=1e-6)
        self.register_buffer("passive_axes", paxes.float())
        self.register_buffer("passive_index", torch.tensor(passive_dofs, dtype=torch.long))
        self.register_buffer("active_index", torch.tensor(self.active_dofs, dtype=torch.long))
        self.register_buffer("passive_lower", sk.lower[self.passive_index].clone())
        self.register_buffer("passive_upper", sk.upper[self.passive_index].clone())
        self.register_buffer("_bone_index", torch.tensor(
            [names.index(b) for b in self.sensor_bones], dtype=torch.long), persistent=False)
        self.register_buffer("sensor_to_bone", torch.eye(3).expand(S, 3, 3).clone())

    # ------------------------------------------------------------------ g and the forward model
    def forward(self, theta: torch.Tensor) -> torch.Tensor:
        """``g(theta)``: the active coordinates ``(*, d)`` of poses ``(*, D)``."""
        self._check_theta(theta)
        return theta.index_select(-1, self.active_index)

    g = forward

    def _check_theta(self, theta: torch.Tensor) -> None:
        if not isinstance(theta, torch.Tensor):
            raise TypeError(f"theta: expected a torch.Tensor, got {type(theta).__name__}")
        if theta.dim() < 1 or theta.shape[-1] != self.num_dofs:
            raise ValueError(f"theta: expected shape (*, {self.num_dofs}), got "
                             f"{tuple(theta.shape)}")

    def bone_orientations(self, theta: torch.Tensor) -> torch.Tensor:
        """Tracking bone orientations ``R_TB`` of the sensor bones, ``(*, S, 3, 3)``."""
        self._check_theta(theta)
        return self.skeleton(theta).rotations.index_select(-3, self._bone_index)

    def sensor_orientations(self, theta: torch.Tensor) -> torch.Tensor:
        """Orientations ``R_TS = R_TB R_SB^T`` that perfect sensors would read, ``(*, S, 3, 3)``."""
        R_tb = self.bone_orientations(theta)
        return R_tb @ self.sensor_to_bone.to(R_tb.dtype).transpose(-1, -2)

    @torch.no_grad()
    def calibrate(self, theta0: torch.Tensor, sensors0: torch.Tensor) -> torch.Tensor:
        """Set ``R_SB = R_TS,0^T R_TB,0`` (eq. 8) from a frame with known pose.

        Args:
            theta0: ``(D,)`` pose of the calibration frame.
            sensors0: ``(S, 3, 3)`` or ``(S, 4)`` sensor orientations of that frame.
        Returns:
            the new ``sensor_to_bone`` ``(S, 3, 3)``.
        """
        if theta0.dim() != 1:
            raise ValueError(f"theta0: expected a single pose (D,), got {tuple(theta0.shape)}")
        R_ts = sensor_rotations(sensors0, self.num_sensors)
        if R_ts.dim() != 3:
            raise ValueError(f"sensors0: expected a single frame, got {tuple(sensors0.shape)}")
        R_tb = self.bone_orientations(theta0.to(R_ts.dtype))
        self.sensor_to_bone = (R_ts.transpose(-1, -2) @ R_tb).to(self.sensor_to_bone.dtype)
        return self.sensor_to_bone

    # ------------------------------------------------------------------ g^{-1}
    def _local_rotations(self, theta: torch.Tensor) -> torch.Tensor:
        """Local rotations of the needed active joints + an identity slot: ``(B, N+1, 3, 3)``."""
        dtype = theta.dtype
        B = theta.shape[0]
        eye = torch.eye(3, dtype=dtype, device=theta.device)
        n = self._need_dofs.shape[0]
        if n == 0:
            return eye.expand(B, 1, 3, 3)
        ang = theta[:, self._need_dofs]  # (B, N, nd)
        s = torch.sin(ang)[..., None, None]
        c1 = (1 - torch.cos(ang))[..., None, None]
        Rd = eye + s * self._need_K.to(dtype) + c1 * self._need_K2.to(dtype)  # (B, N, nd, 3, 3)
        L = Rd[:, :, 0]
        for k in range(1, Rd.shape[2]):
            L = L @ Rd[:, :, k]
        return torch.cat([L, eye.expand(B, 1, 3, 3)], dim=1)

    def inverse(
        self,
        x_a: torch.Tensor,
        sensors: torch.Tensor,
        reference: torch.Tensor | None = None,
        compute_residual: bool = True,
        sensor_frame: bool = True,
        validate: bool = True,
    ) -> ManifoldSolution:
        """``g^{-1}(x_a, sensors)``: full poses from active coordinates and sensor orientations.

        Args:
            x_a: ``(*, d)`` active coordinates.
            sensors: ``(*, S, 3, 3)`` rotations or ``(*, S, 4)`` unit quaternions (w, x, y, z) of
                the sensors in the tracking frame (``R_TS``), broadcast against ``x_a``: one set
                for all particles or one noisy set per particle.
            reference: optional ``(*, D)`` or ``(D,)`` pose; of the two solutions per passive
                joint, one inside the joint limits is preferred, then the one closest to the
                reference's passive angles (default: the rest pose, zeros). Under gimbal lock the
                first passive angle is taken from it.
            compute_residual: also return the per-sensor residual angles.
            sensor_frame: ``sensors`` are sensor orientations (``R_SB`` applied); pass False to
                give sensor *bone* orientations ``R_TB`` directly.
            validate: check shapes and values (disable in hot loops with trusted inputs).
        Returns:
            :class:`ManifoldSolution` (``theta (*, D)``, ``residual (*, S)``, ...).
        """
        S, d = self.num_sensors, self.num_active
        if validate:
            if not isinstance(x_a, torch.Tensor) or x_a.dim() < 1 or x_a.shape[-1] != d:
                shape = tuple(x_a.shape) if isinstance(x_a, torch.Tensor) else type(x_a).__name__
                raise ValueError(f"x_a: expected shape (*, {d}) active coordinates, got {shape}")
            if not bool(torch.isfinite(x_a).all()):
                raise ValueError("x_a: expected finite values, found NaN or inf")
            R_ts = sensor_rotations(sensors, S)
        else:
            R_ts = quaternion_to_matrix(sensors) if sensors.shape[-1] == 4 else sensors
        dtype, device = x_a.dtype, x_a.device
        R_ts = R_ts.to(dtype)
        batch = torch.broadcast_shapes(x_a.shape[:-1], R_ts.shape[:-3])
        B = math.prod(batch)
        xa = x_a.expand(*batch, d).reshape(B, d)
        B_req = R_ts.expand(*batch, S, 3, 3).reshape(B, S, 3, 3)
        if sensor_frame:
            B_req = B_req @ self.sensor_to_bone.to(dtype)  # R_TS R_SB, eq. 9
        theta = xa.new_zeros(B, self.num_dofs)
        theta[:, self.active_index] = xa
        if reference is not None:
            if reference.shape[-1] != self.num_dofs:
                raise ValueError(f"reference: expected shape (*, {self.num_dofs}), got "
                                 f"{tuple(reference.shape)}")
            ref_p = reference.to(dtype)[..., self.passive_index]  # (*, S, 3)
            ref_p = ref_p.expand(*batch, S, 3).reshape(B, S, 3)
        else:
            ref_p = None

        loc = self._local_rotations(theta)  # (B, N+1, 3, 3)
        # R_pj: upstream bone orientation (or identity) times the active chain above j
        if self._has_upstream:
            up = self._upstream.clamp(min=0)
            eye = torch.eye(3, dtype=dtype, device=device)
            U = B_req[:, up]
            Rp = torch.where((self._upstream >= 0)[None, :, None, None], U, eye)
        else:
            Rp = None
        for k in range(self._above.shape[1]):
            Lk = loc[:, self._above[:, k]]
            Rp = Lk if Rp is None else Rp @ Lk
        Rc = None
        for k in range(self._below.shape[1]):
            Lk = loc[:, self._below[:, k]]
            Rc = Lk if Rc is None else Rc @ Lk
        Lj = B_req if Rp is None else Rp.transpose(-1, -2) @ B_req
        if Rc is not None:
            Lj = Lj @ Rc.transpose(-1, -2)  # eq. 11

        axes = self.passive_axes.to(dtype)
        default_t1 = ref_p[..., 0] if ref_p is not None else None
        if self._orthogonal:
            cand, gimbal = orthogonal_three_axis_decomposition(Lj, axes, default_t1)
        else:
            res = three_axis_decomposition(Lj, axes[:, 0], axes[:, 1], axes[:, 2],
                                           default_theta1=default_t1, compute_residual=False)
            cand, gimbal = res.angles, res.gimbal
        cand = self._wrap_into_limits(cand)  # (B, S, 2, 3)
        lo = self.passive_lower.to(dtype)[:, None]
        hi = self.passive_upper.to(dtype)[:, None]
        inside = ((cand >= lo) & (cand <= hi)).all(-1)  # (B, S, 2)
        ref = ref_p[:, :, None] if ref_p is not None else torch.zeros((), dtype=dtype)
        diff = torch.remainder(cand - ref + math.pi, 2 * math.pi) - math.pi
        score = diff.abs().sum(-1) + 100.0 * (~inside).to(dtype)
        pick = (score[..., 1] < score[..., 0])  # (B, S)
        chosen = torch.where(pick[..., None], cand[:, :, 1], cand[:, :, 0])
        within = torch.where(pick, inside[..., 1], inside[..., 0])
        theta = theta.index_put((torch.arange(B, device=device)[:, None, None],
                                 self.passive_index[None]), chosen)

        residual = None
        if compute_residual:
            residual = self._residual(chosen, Rp, Rc, B_req, axes).reshape(*batch, S)
        return ManifoldSolution(
            theta=theta.reshape(*batch, self.num_dofs),
            residual=residual,
            within_limits=within.reshape(*batch, S),
            gimbal=gimbal.reshape(*batch, S),
        )

    def _wrap_into_limits(self, cand: torch.Tensor) -> torch.Tensor:
        """Shift angles by ``+-2 pi`` where that brings them inside limits reaching past ``pi``."""
        lo = self.passive_lower.to(cand.dtype)[:, None]
        hi = self.passive_upper.to(cand.dtype)[:, None]
        two_pi = 2 * math.pi
        up = (cand < lo) & (cand + two_pi <= hi)
        dn = (cand > hi) & (cand - two_pi >= lo)
        return cand + two_pi * (up.to(cand.dtype) - dn.to(cand.dtype))

    def _residual(self, chosen, Rp, Rc, B_req, axes) -> torch.Tensor:
        """Angle between achieved and requested sensor-bone orientations ``(B, S)``.

        Upstream bones enter with their *achieved* orientation (level by level)."""
        from torchmocap.geometry import axis_angle_rotation

        Rax = axis_angle_rotation(axes.expand(*chosen.shape[:-1], 3, 3), chosen)
        Lj = Rax[..., 0, :, :] @ Rax[..., 1, :, :] @ Rax[..., 2, :, :]
        # local part below the upstream bone: A (active chain above j) L_j R_cj
        dtype = chosen.dtype
        if Rp is not None and self._has_upstream:
            # Rp = U A  =>  A = U^T Rp for sensors with an upstream bone
            up = self._upstream.clamp(min=0)
            has_up = (self._upstream >= 0)[None, :, None, None]
            A = torch.where(has_up, B_req[:, up].transpose(-1, -2) @ Rp, Rp)
        else:
            A = Rp
        part = Lj if A is None else A @ Lj
        if Rc is not None:
            part = part @ Rc
        achieved = torch.empty_like(part)
        for lv, idx in enumerate(self._levels):
            ii = torch.tensor(idx, device=part.device)
            if lv == 0:
                achieved[:, ii] = part[:, ii]
            else:
                achieved[:, ii] = achieved[:, self._upstream[ii]] @ part[:, ii]
        M = achieved.transpose(-1, -2) @ B_req
        skew = torch.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0],
                            M[..., 1, 0] - M[..., 0, 1]], dim=-1)
        tr = M.diagonal(dim1=-2, dim2=-1).sum(-1)
        del dtype
        return torch.atan2(0.5 * skew.norm(dim=-1), 0.5 * (tr - 1))

    def extra_repr(self) -> str:
        pairs = ", ".join(f"{s}->{b} (passive {j})" for s, b, j in
                          zip(self.sensor_names, self.sensor_bones, self.passive_joints))
        return f"sensors=[{pairs}], active={self.num_active}/{self.num_dofs}"
