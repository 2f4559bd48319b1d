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

from torchmocap.compilation import CompiledFunction
from torchmocap.geometry import quaternion_to_matrix, wrap_angle
from torchmocap.geometry.subproblems import (
    axes_are_orthogonal,
    three_axis_decomposition,
)
from torchmocap.stateful import Stateful

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


def _rotation_tol(dtype: torch.dtype) -> float:
    """Largest accepted deviation of a rotation from orthonormality / a quaternion from unit
    norm: ~1000 ulp of float32 (rounding of long products), 1e-6 in float64."""
    if dtype == torch.float64:
        return 1e-6
    if dtype == torch.float32:
        return 1e-4
    return 1e-2  # half precisions


def _first_bad(bad: torch.Tensor) -> str:
    """``"sensor s (batch index i)"`` of the first True entry of ``bad (*, S)``."""
    idx = [int(v) for v in torch.nonzero(bad)[0].tolist()]
    where = f"sensor {idx[-1]}"
    return where if len(idx) == 1 else f"{where} (batch index {tuple(idx[:-1])})"


def sensor_rotations(sensors: torch.Tensor, num_sensors: int,
                     name: str = "sensors") -> torch.Tensor:
    """Validate sensor orientations and return rotation matrices ``(*, S, 3, 3)``.

    Rotation matrices must be orthonormal with determinant +1 (``|R Rᵀ - I|`` and ``|det R - 1|``
    at most 1e-4 in float32, 1e-6 in float64): ``2 R``, zero matrices, reflections or skewed
    matrices would give valid-looking, wrong joint angles. Quaternions must be finite and of
    unit norm within the same tolerance. The check is a few elementwise passes and one host
    sync; ``SensorManifold.inverse(validate=False)`` skips it in hot loops.

    Args:
        sensors: ``(*, S, 3, 3)`` rotation matrices or ``(*, S, 4)`` unit quaternions (w, x, y, z).
        num_sensors: expected ``S``.
        name: the argument's name in error messages (``sensors``, ``sensors0``, ``noise``).
    """
    if not isinstance(sensors, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(sensors).__name__}")
    if not sensors.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {sensors.dtype}")
    tol = _rotation_tol(sensors.dtype)
    if sensors.dim() >= 2 and sensors.shape[-1] == 4:
        if sensors.shape[-2] != num_sensors:
            raise ValueError(f"{name}: expected {num_sensors} sensors (*, {num_sensors}, 4), "
                             f"got shape {tuple(sensors.shape)}")
        norm = sensors.norm(dim=-1)
        dev = (norm - 1).abs()
        if sensors.numel() and not float(dev.max()) <= tol:  # one sync; NaN fails it too
            if not bool(torch.isfinite(sensors).all()):
                raise ValueError(f"{name}: expected finite quaternions, found NaN or inf")
            bad = dev > tol
            i = tuple(torch.nonzero(bad)[0].tolist())
            raise ValueError(f"{name}: expected unit quaternions (w, x, y, z), tolerance {tol}; "
                             f"{_first_bad(bad)} has norm {float(norm[i]):.6g}")
        return quaternion_to_matrix(sensors)
    if sensors.dim() >= 3 and sensors.shape[-2:] == (3, 3):
        if sensors.shape[-3] != num_sensors:
            raise ValueError(f"{name}: expected {num_sensors} sensors (*, {num_sensors}, 3, 3), "
                             f"got shape {tuple(sensors.shape)}")
        if sensors.numel():
            # R Rᵀ = I and det R = (r0 x r1) . r2 = +1; one sync for both (NaN fails it too)
            gram = sensors @ sensors.transpose(-1, -2)
            eye = torch.eye(3, dtype=sensors.dtype, device=sensors.device)
            orth = (gram - eye).abs().amax(dim=(-1, -2))
            det = (torch.linalg.cross(sensors[..., 0, :], sensors[..., 1, :])
                   * sensors[..., 2, :]).sum(-1)
            dev = torch.maximum(orth, (det - 1).abs())
            worst = float(dev.max())
            if not worst <= tol:
                if not bool(torch.isfinite(sensors).all()):
                    raise ValueError(f"{name}: expected finite rotation matrices, found NaN or "
                                     "inf")
                bad = dev > tol
                i = tuple(torch.nonzero(bad)[0].tolist())
                raise ValueError(
                    f"{name}: expected rotation matrices (R Rᵀ = I, det R = +1, tolerance {tol}); "
                    f"{_first_bad(bad)} has |R Rᵀ - I| = {float(orth[i]):.3g}, "
                    f"det = {float(det[i]):.6g}")
        return sensors
    raise ValueError(f"{name}: expected (*, {num_sensors}, 3, 3) rotations or "
                     f"(*, {num_sensors}, 4) quaternions, got {tuple(sensors.shape)}")


def _mm(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Product of rotation batches in the (3, 3, ...) layout (broadcast over trailing dims)."""
    return (A[:, :, None] * B[None]).sum(1)


def _euler_candidates(M: torch.Tensor, h: torch.Tensor, default_t1: torch.Tensor | None):
    """Both solutions of ``Rx(a) Ry(b) Rz(c) = M`` for ``M (3, 3, S, B)`` (see
    :func:`~torchmocap.geometry.subproblems.orthogonal_three_axis_decomposition`); returns
    ``(3, 2, S, B)`` angles ``(a, b, h c)`` and the gimbal flag ``(S, B)``."""
    m12, m22 = M[1, 2], M[2, 2]
    n2 = m12 * m12 + m22 * m22
    tiny = (16 * torch.finfo(M.dtype).eps) ** 2
    lock = n2 <= tiny
    gimbal = n2 <= (1e-9 if M.dtype == torch.float64 else 1e-4)
    a = torch.atan2(-m12, torch.where(lock, torch.ones_like(m22), m22))
    if default_t1 is not None:
        a = torch.where(lock, default_t1.to(a).expand_as(a), a)
    else:
        a = torch.where(lock, torch.zeros_like(a), a)
    ca, sa = torch.cos(a), torch.sin(a)
    b = torch.atan2(M[0, 2], ca * m22 - sa * m12)
    c = torch.atan2(ca * M[1, 0] + sa * M[2, 0], ca * M[1, 1] + sa * M[2, 1])
    pi = math.pi
    a2 = torch.where(a > 0, a - pi, a + pi)
    b2 = torch.where(b >= 0, pi - b, -pi - b)
    c2 = torch.where(c > 0, c - pi, c + pi)
    first = torch.stack([a, b, h * c])
    second = torch.stack([a2, b2, h * c2])
    return torch.stack([first, second], dim=1), gimbal


class SensorManifold(nn.Module, Stateful):
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

        # --- structure-of-arrays constants of the fast g^{-1} core
        apos = {dof: i for i, dof in enumerate(self.active_dofs)}
        self.register_buffer("_need_xa", torch.tensor(
            [[apos[d] for d in row] for row in dof_idx], dtype=torch.long).reshape(
            len(needed), nd), persistent=False)
        self.register_buffer("_soa_K", K.permute(2, 3, 0, 1)[..., None].contiguous(),
                             persistent=False)  # (3, 3, N, nd, 1)
        self.register_buffer("_soa_K2", (K @ K).permute(2, 3, 0, 1)[..., None].contiguous(),
                             persistent=False)
        PK = hat(paxes.float())  # (S, 3, 3, 3): sensor, axis, matrix
        self.register_buffer("_soa_PK", PK.permute(2, 3, 1, 0)[..., None].contiguous(),
                             persistent=False)  # (3, 3, 3 axes, S, 1)
        self.register_buffer("_soa_PK2", (PK @ PK).permute(2, 3, 1, 0)[..., None].contiguous(),
                             persistent=False)
        e3 = torch.linalg.cross(paxes[:, 0], paxes[:, 1])
        E = torch.stack([paxes[:, 0], paxes[:, 1], e3], dim=-1)  # (S, 3, 3) columns
        self.register_buffer("_soa_E", E.float().permute(1, 2, 0)[..., None].contiguous(),
                             persistent=False)
        self.register_buffer("_soa_h", (e3 * paxes[:, 2]).sum(-1).float()[:, None],
                             persistent=False)
        lo_t = self.passive_lower.t()[:, None, :, None]  # (3, 1, S, 1)
        hi_t = self.passive_upper.t()[:, None, :, None]
        self.register_buffer("_soa_lower", lo_t.contiguous(), persistent=False)
        self.register_buffer("_soa_upper", hi_t.contiguous(), persistent=False)
        self._limits_past_pi = bool((self.passive_upper > math.pi).any()
                                    or (self.passive_lower < -math.pi).any())
        order_cat = self.active_dofs + flat_passive
        assemble = [order_cat.index(dof) for dof in range(sk.num_dofs)]
        self.register_buffer("_assemble", torch.tensor(assemble, dtype=torch.long),
                             persistent=False)
        self.register_buffer("_has_up_mask", self._upstream >= 0, persistent=False)
        self._levels_t = [torch.tensor(ix, dtype=torch.long) for ix in self._levels]
        # R(q)_kl = sum_ab Q[k, l, a, b] q_a q_b for unit quaternions (w, x, y, z)
        Q = torch.zeros(3, 3, 4, 4)
        terms = {
            (0, 0): [(0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)],
            (1, 1): [(0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)],
            (2, 2): [(0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)],
            (0, 1): [(1, 2, 2), (0, 3, -2)], (0, 2): [(1, 3, 2), (0, 2, 2)],
            (1, 0): [(1, 2, 2), (0, 3, 2)], (1, 2): [(2, 3, 2), (0, 1, -2)],
            (2, 0): [(1, 3, 2), (0, 2, -2)], (2, 1): [(2, 3, 2), (0, 1, 2)],
        }
        for (k, l_), ts in terms.items():
            for a, b, v in ts:
                Q[k, l_, a, b] += v
        self.register_buffer("_quat_quadratic", Q, persistent=False)

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

    def checkpoint_state(self) -> dict[str, torch.Tensor]:
        """The calibration ``sensor_to_bone`` (:meth:`calibrate`), saved in a tracker's
        checkpoints (:class:`~torchmocap.stateful.Stateful`)."""
        return {"sensor_to_bone": self.sensor_to_bone.detach().clone()}

    def load_checkpoint_state(self, state: dict[str, torch.Tensor]) -> None:
        self.sensor_to_bone = state["sensor_to_bone"]

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
        R_ts = sensor_rotations(sensors0, self.num_sensors, "sensors0")
        if R_ts.dim() != 3:
            raise ValueError(f"sensors0: expected a single frame, got {tuple(sensors0.shape)}")
        R_tb = self.bone_orientations(theta0.to(R_ts.dtype))
        self.sensor_to_bone = (R_ts.transpose(-1, -2) @ R_tb).to(self.sensor_to_bone.dtype)
        return self.sensor_to_bone

    # ------------------------------------------------------------------ g^{-1}
    # The core works in a structure-of-arrays layout: a batch of rotations is (3, 3, S, B)
    # (sensors S, batch B last), products are broadcast multiply + sum over the inner index.
    # Batched 3x3 ``bmm`` on CPU costs ~60 us per 1000 matrices; this costs ~15 us.

    def _soa_local_rotations(self, xa: torch.Tensor) -> torch.Tensor:
        """Local rotations of the needed active joints + identity slot, ``(3, 3, N+1, B)``."""
        dtype = xa.dtype
        B = xa.shape[0]
        eye = torch.eye(3, dtype=dtype, device=xa.device)[:, :, None, None]
        n = self._need_xa.shape[0]
        if n == 0:
            return eye.expand(3, 3, 1, B)
        ang = xa.t().contiguous()[self._need_xa]  # (N, nd, B)
        s = torch.sin(ang)
        c1 = 1 - torch.cos(ang)
        Rd = eye[..., None] + s * self._soa_K.to(dtype) + c1 * self._soa_K2.to(dtype)
        L = Rd[:, :, :, 0]
        for k in range(1, Rd.shape[3]):
            L = _mm(L, Rd[:, :, :, k])
        return torch.cat([L, eye.expand(3, 3, 1, B)], dim=2)

    def _soa_bone_requests(
        self, R_ts: torch.Tensor, noise: torch.Tensor | None, B: int, sensor_frame: bool
    ) -> torch.Tensor:
        """Requested sensor-bone orientations ``R_TS R_w R_SB`` as ``(3, 3, S, B)``."""
        dtype = R_ts.dtype
        S = self.num_sensors
        C2 = self.sensor_to_bone.to(dtype) if sensor_frame else None
        if noise is not None and noise.shape[-1] == 4 and R_ts.dim() == 3:
            # shared sensors, quaternion noise: R_TS R(q) R_SB is a quadratic form in q with a
            # per-sensor (9, 16) coefficient matrix -> one batched GEMM
            Q = self._quat_quadratic.to(dtype)  # (3, 3, 4, 4)
            left = R_ts
            right = C2 if C2 is not None else torch.eye(3, dtype=dtype, device=R_ts.device)
            right = right.expand(S, 3, 3)
            # coef[s, i, j, ab] = sum_kl left[s, i, k] Q[k, l, ab] right[s, l, j]; broadcast
            # sums (a GEMM call costs ~100 us here for these 720 numbers)
            Qf = Q.reshape(1, 1, 3, 3, 16)
            X1 = (left[:, :, :, None, None] * Qf).sum(2)  # [s, i, l, ab]
            coef = (X1[:, :, :, None, :] * right[:, None, :, :, None]).sum(2)  # [s, i, j, ab]
            coef = coef.reshape(S, 9, 16)
            q = noise.expand(B, S, 4) if noise.dim() == 2 else noise.reshape(B, S, 4)
            qq = (q[..., :, None] * q[..., None, :]).reshape(B, S, 16).permute(1, 2, 0)
            return torch.bmm(coef, qq).reshape(S, 3, 3, B).permute(1, 2, 0, 3)
        X = R_ts.expand(B, S, 3, 3) if R_ts.dim() == 3 else R_ts.reshape(B, S, 3, 3)
        X = X.permute(2, 3, 1, 0)  # (3, 3, S, B)
        if noise is not None:
            W = noise
            if W.shape[-1] == 4:
                W = torch.einsum("klab,...a,...b->...kl", self._quat_quadratic.to(dtype), W, W)
            W = W.to(dtype).expand(B, S, 3, 3) if W.dim() == 3 else W.reshape(B, S, 3, 3)
            X = _mm(X, W.permute(2, 3, 1, 0))
        if C2 is not None:
            X = _mm(X, C2.permute(1, 2, 0)[..., None])
        return X

    def inverse(
        self,
        x_a: torch.Tensor,
        sensors: torch.Tensor,
        reference: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
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
            noise: optional ``(*, S, 4)`` unit quaternions or ``(*, S, 3, 3)`` rotations applied
                on the right of the sensor orientations, ``R_TS R_w`` (eq. 16). Passing the
                noise separately from shared ``sensors`` is the fast path (one GEMM).
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
            if noise is not None:
                sensor_rotations(noise, S, "noise")  # same checks as the sensors
        else:
            R_ts = quaternion_to_matrix(sensors) if sensors.shape[-1] == 4 else sensors
        dtype = x_a.dtype
        R_ts = R_ts.to(dtype)
        if noise is not None:
            noise = noise.to(dtype)
            nb = noise.shape[:-2] if noise.shape[-1] == 4 else noise.shape[:-3]
        else:
            nb = ()
        batch = torch.broadcast_shapes(x_a.shape[:-1], R_ts.shape[:-3], nb)
        B = math.prod(batch)
        xa = x_a.expand(*batch, d).reshape(B, d)
        if R_ts.dim() > 3:
            R_ts = R_ts.expand(*batch, S, 3, 3).reshape(B, S, 3, 3)
        if noise is not None and len(nb) and tuple(nb) != (B,):
            noise = noise.expand(*batch, *noise.shape[len(nb):]).reshape(B, *noise.shape[len(nb):])
        if reference is not None:
            if reference.shape[-1] != self.num_dofs:
                raise ValueError(f"reference: expected shape (*, {self.num_dofs}), got "
                                 f"{tuple(reference.shape)}")
            ref = reference.to(dtype).reshape(-1, self.num_dofs)
            if ref.shape[0] not in (1, B):
                ref = reference.to(dtype).expand(*batch, self.num_dofs).reshape(B, -1)
        else:
            ref = None
        solve = self.__dict__.get("_solve_impl") or self._solve
        theta, residual, within, gimbal = solve(xa, R_ts, noise, ref, compute_residual,
                                                sensor_frame)
        return ManifoldSolution(
            theta=theta.reshape(*batch, self.num_dofs),
            residual=None if residual is None else residual.t().reshape(*batch, S),
            within_limits=within.t().reshape(*batch, S),
            gimbal=gimbal.t().reshape(*batch, S),
        )

    def compile_inverse(self) -> SensorManifold:
        """Compile the ``g^{-1}`` core with ``torch.compile(dynamic=True)``
        (:class:`~torchmocap.compilation.CompiledFunction`: eager again if compiling fails).

        The first call per input signature compiles (tens of seconds on a CPU); afterwards
        the ~150 small tensor operations run as a few fused kernels. Returns ``self``."""
        self.__dict__["_solve_impl"] = CompiledFunction(self._solve, "proposal.compile",
                                                        dynamic=True)
        return self

    def _solve(
        self,
        xa: torch.Tensor,
        R_ts: torch.Tensor,
        noise: torch.Tensor | None,
        ref: torch.Tensor | None,
        compute_residual: bool,
        sensor_frame: bool,
    ):
        """Core of :meth:`inverse` on flat inputs: ``xa (B, d)``, ``R_ts (S, 3, 3)`` or
        ``(B, S, 3, 3)``, ``noise (B, S, 4 | 3, 3)`` or None, ``ref (1 | B, D)`` or None.
        Returns ``theta (B, D)``, ``residual (S, B)`` or None, ``within (S, B)``,
        ``gimbal (S, B)``."""
        S = self.num_sensors
        B = xa.shape[0]
        dtype, device = xa.dtype, xa.device
        Breq = self._soa_bone_requests(R_ts, noise, B, sensor_frame)  # (3, 3, S, B)
        ref_p = ref.t().contiguous()[self.passive_index] if ref is not None else None
        loc = self._soa_local_rotations(xa)  # (3, 3, N+1, B)
        # X = R_pj^T B_req R_cj^T with R_pj = U A (U: upstream bone request, A: active chain)
        X = Breq
        if self._has_upstream:
            U = Breq[:, :, self._upstream.clamp(min=0)]
            eye = torch.eye(3, dtype=dtype, device=device)[:, :, None, None]
            U = torch.where(self._has_up_mask[None, None, :, None], U, eye)
            X = _mm(U.transpose(0, 1), X)
        A = None
        for k in range(self._above.shape[1]):
            Lk = loc[:, :, self._above[:, k]]
            A = Lk if A is None else _mm(A, Lk)
        if A is not None:
            X = _mm(A.transpose(0, 1), X)
        Rc = None
        for k in range(self._below.shape[1]):
            Lk = loc[:, :, self._below[:, k]]
            Rc = Lk if Rc is None else _mm(Rc, Lk)
        if Rc is not None:
            X = _mm(X, Rc.transpose(0, 1))  # L_j, eq. 11, (3, 3, S, B)

        E = self._soa_E.to(dtype)  # (3, 3, S, 1), columns w1, w2, w1 x w2
        M = _mm(_mm(E.transpose(0, 1), X), E)
        default_t1 = ref_p[:, 0] if ref_p is not None else None
        if self._orthogonal:
            cand, gimbal = _euler_candidates(M, self._soa_h.to(dtype), default_t1)
        else:
            Laos = X.permute(3, 2, 0, 1)  # (B, S, 3, 3)
            axes = self.passive_axes.to(dtype)
            dt1 = default_t1.t().expand(B, S) if default_t1 is not None else None
            res = three_axis_decomposition(Laos, axes[:, 0], axes[:, 1], axes[:, 2],
                                           default_theta1=dt1, compute_residual=False)
            cand = res.angles.permute(3, 2, 1, 0)  # (3, 2, S, B)
            gimbal = res.gimbal.t()
        # cand: (3, 2, S, B) -- angle, solution, sensor, batch
        two_pi = 2 * math.pi
        lo, hi = self._soa_lower.to(dtype), self._soa_upper.to(dtype)  # (3, 1, S, 1)
        up = (cand < lo) & (cand + two_pi <= hi)
        dn = (cand > hi) & (cand - two_pi >= lo)
        if self._limits_past_pi:
            cand = cand + two_pi * (up.to(dtype) - dn.to(dtype))
        inside = ((cand >= lo) & (cand <= hi)).all(0)  # (2, S, B)
        r = ref_p.transpose(0, 1)[:, None].contiguous() if ref_p is not None else 0.0
        diff = wrap_angle(cand - r)
        score = diff.abs().sum(0) + 100.0 * (~inside).to(dtype)  # (2, S, B)
        pick = score[1] < score[0]  # (S, B)
        chosen = torch.where(pick, cand[:, 1], cand[:, 0])  # (3, S, B)
        within = torch.where(pick, inside[1], inside[0])
        passive_flat = chosen.permute(2, 1, 0).reshape(B, 3 * S)
        theta = torch.cat([xa, passive_flat], dim=-1).index_select(-1, self._assemble)

        residual = self._soa_residual(chosen, X, A, Rc) if compute_residual else None
        return theta, residual, within, gimbal

    def _soa_residual(self, chosen, L_req, A, Rc) -> torch.Tensor:
        """Angle ``(S, B)`` between achieved and requested sensor-bone orientations.

        Error of sensor s in its bone frame: ``G_s = R_c^T L_ach^T A^T G_u A L_req R_c`` with the
        upstream bone's error ``G_u`` (identity without upstream sensor)."""
        dtype = chosen.dtype
        ang = chosen  # (3, S, B)
        s = torch.sin(ang)
        c1 = 1 - torch.cos(ang)
        eye = torch.eye(3, dtype=dtype, device=ang.device)[:, :, None, None, None]
        Rd = eye + s * self._soa_PK.to(dtype) + c1 * self._soa_PK2.to(dtype)  # (3,3,3,S,B)
        L_ach = _mm(_mm(Rd[:, :, 0], Rd[:, :, 1]), Rd[:, :, 2])
        H = _mm(L_ach.transpose(0, 1), L_req)  # no upstream error, no A
        if self._has_upstream:
            G = torch.empty_like(H)
            for lv, idx in enumerate(self._levels_t):
                idx = idx.to(H.device)
                if lv == 0:
                    Hs = H[:, :, idx]
                else:
                    Gu = G[:, :, self._upstream.to(H.device)[idx]]
                    Au = A[:, :, idx] if A is not None else None
                    inner = _mm(_mm(Au.transpose(0, 1), Gu), Au) if Au is not None else Gu
                    Hs = _mm(_mm(L_ach[:, :, idx].transpose(0, 1), inner), L_req[:, :, idx])
                H[:, :, idx] = Hs
                G[:, :, idx] = (_mm(_mm(Rc[:, :, idx].transpose(0, 1), Hs), Rc[:, :, idx])
                                if Rc is not None else Hs)
        skew = torch.stack([H[2, 1] - H[1, 2], H[0, 2] - H[2, 0], H[1, 0] - H[0, 1]], dim=0)
        tr = H[0, 0] + H[1, 1] + H[2, 2]
        return torch.atan2(0.5 * skew.norm(dim=0), 0.5 * (tr - 1))

    def extra_repr(self) -> str:
        pairs = ", ".join(f"{s}->{b} (passive {j})" for s, b, j in
                          zip(self.sensor_names, self.sensor_bones, self.passive_joints))
        return f"sensors=[{pairs}], active={self.num_active}/{self.num_dofs}"
