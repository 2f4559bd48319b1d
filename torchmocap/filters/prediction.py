"""Third-order autoregressive pose prediction (Pons-Moll §4.3: particles are predicted from the
last three estimates), with rotation coordinates composed on SO(3).

History is chronological: ``history (..., T, D)`` with ``T ≥ 3``; only the last three rows are
used, ``x1 = history[..., -1, :]`` (t−1, most recent), ``x2`` (t−2), ``x3`` (t−3). With
``Δ1 = x1 − x2`` and ``Δ2 = x2 − x3``, the scalar modes are

- ``constant_acceleration``: ``x̂ = 3x1 − 3x2 + x3 = x1 + Δ1 + (Δ1 − Δ2)`` (exact on quadratics,
  but it amplifies i.i.d. noise by √19 ≈ 4.4);
- ``damped``: ``x̂ = x1 + λ1 Δ1 + λ2 (Δ1 − Δ2)`` (λ = (1, 1) is constant acceleration, (1, 0)
  constant velocity, (0, 0) constant position).

**Rotation groups.** Angles must not be extrapolated as numbers: a rotation vector that wraps
from +π to −π, or Euler-type angles through arbitrary axes, break linear extrapolation. A
:class:`RotationGroup` names three coordinates; they are mapped to rotations ``R1, R2, R3`` and
the *relative* increments ``δ1 = log(R2ᵀ R1)``, ``δ2 = log(R3ᵀ R2)`` are extrapolated the same
way (``δ̂ = u δ1 + v δ2``; constant acceleration ``u = 2, v = −1``; damped ``u = λ1 + λ2,
v = −λ2``), then composed: ``R̂ = R1 exp(δ̂)``. A constant-rate rotation is predicted exactly.

Finally the prediction is clamped to ``[lower, upper]`` (e.g. ``skeleton.lower/upper``).

Shapes: ``T`` frames of history, ``D`` pose dims, ``G`` rotation groups.

Example:
    >>> h = torch.tensor([[0.0], [1.0], [4.0]])  # x = t², t = 0, 1, 2
    >>> predict_ar3(h, "constant_acceleration")
    tensor([9.])
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from torchmocap.geometry import axis_angle_rotation, so3_exp, so3_log

__all__ = [
    "RotationGroup",
    "skeleton_rotation_groups",
    "PosePredictor",
    "predict_ar3",
    "angles_from_matrix",
    "euler_matrix",
    "MODES",
]

MODES = ("constant_acceleration", "damped")

ToMatrix = Callable[[torch.Tensor], torch.Tensor]
FromMatrix = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _rotvec_from_matrix(R: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    return so3_log(R)


def angles_from_matrix(
    to_matrix: ToMatrix,
    R: torch.Tensor,
    reference: torch.Tensor,
    iterations: int = 20,
    tol: float = 1e-12,
) -> torch.Tensor:
    """Three angles ``θ (..., 3)`` with ``to_matrix(θ) = R``, the solution nearest ``reference``.

    Generic inverse of any 3-parameter rotation map (Euler-type angles through arbitrary axes):
    damped Gauss–Newton on the residual ``log(to_matrix(θ)ᵀ R)`` started at ``reference``, with
    a central-difference Jacobian, in float64 (``to_matrix`` is called with float64 angles, so
    it must follow its input's dtype). Because it starts at the reference (the previous
    frame's angles), it picks the branch and the ``2π`` winding closest to it — the angles come
    out continuous, not wrapped into ``(−π, π]``. Near gimbal lock the damping returns a valid
    decomposition of ``R`` (only ``t1 ± t3`` is determined there).

    Args:
        to_matrix: ``(..., 3) -> (..., 3, 3)``.
        R: target rotations ``(..., 3, 3)``.
        reference: starting angles ``(..., 3)``.
    Returns:
        ``(..., 3)`` angles in ``reference``'s dtype.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R: expected shape (..., 3, 3), got {tuple(R.shape)}")
    if reference.shape[-1:] != (3,) or reference.shape[:-1] != R.shape[:-2]:
        raise ValueError(
            f"reference: expected shape {(*R.shape[:-2], 3)}, got {tuple(reference.shape)}"
        )
    dtype = reference.dtype
    Rd = R.to(torch.float64)
    th = reference.to(torch.float64).clone()
    eye = torch.eye(3, dtype=torch.float64, device=th.device)
    h = 1e-6

    def resid(t: torch.Tensor) -> torch.Tensor:
        # always float64: the central differences below need it (h = 1e-6)
        M = to_matrix(t).to(torch.float64)
        return so3_log(M.transpose(-1, -2) @ Rd)

    # the point and its six central-difference neighbours, evaluated in one batch
    offsets = torch.cat([torch.zeros(1, 3, dtype=torch.float64, device=th.device),
                         eye * h, -eye * h]).reshape(7, *([1] * (th.dim() - 1)), 3)
    for _ in range(iterations):
        rr = resid(th + offsets)  # (7, ..., 3)
        r = rr[0]
        if float(r.norm(dim=-1).max()) < tol:
            break
        J = ((rr[1:4] - rr[4:7]) / (2 * h)).movedim(0, -1)  # (..., 3, 3): dr_i / dθ_j
        JtJ = J.transpose(-1, -2) @ J
        mu = 1e-10 * (1.0 + JtJ.diagonal(dim1=-2, dim2=-1).sum(-1))
        step = torch.linalg.solve(
            JtJ + mu[..., None, None] * eye, (J.transpose(-1, -2) @ r[..., None])
        )[..., 0]
        # Gauss–Newton (r(θ + Δ) ≈ r + JΔ = 0) with the step capped at 0.5 rad so the
        # iteration stays in the reference's basin
        norm = step.norm(dim=-1, keepdim=True)
        th = th - step * torch.clamp(0.5 / norm.clamp(min=1e-300), max=1.0)
    return th.to(dtype)


def euler_matrix(axes: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """``rot(a1, t1) @ rot(a2, t2) @ rot(a3, t3)`` for unit ``axes (..., 3, 3)`` (rows, batch
    dims broadcast against ``angles``) and ``angles (..., 3)`` → ``(..., 3, 3)``, in the
    angles' dtype and device."""
    a = axes.to(dtype=angles.dtype, device=angles.device)
    batch = torch.broadcast_shapes(a.shape[:-2], angles.shape[:-1])
    a = a.expand(*batch, 3, 3)
    out = axis_angle_rotation(a[..., 0, :], angles[..., 0].expand(batch))
    for j in (1, 2):
        out = out @ axis_angle_rotation(a[..., j, :], angles[..., j].expand(batch))
    return out


@dataclass(frozen=True)
class RotationGroup:
    """Three pose coordinates that together parameterise a rotation.

    Attributes:
        indices: the three coordinate indices into ``D``.
        to_matrix: ``(..., 3) -> (..., 3, 3)``; ``None`` means a rotation vector (``so3_exp``).
        from_matrix: ``(R (..., 3, 3), reference (..., 3)) -> (..., 3)``, the inverse, given the
            previous values as a reference (to pick a branch / winding). ``None`` means
            ``so3_log`` for rotation vectors and :func:`angles_from_matrix` (Gauss–Newton
            started at the reference) when ``to_matrix`` is given.

    Example (root rotation as three angles through the skeleton's root axes)::

        axes = torch.tensor([[0., 0., 1.], [0., 1., 0.], [1., 0., 0.]])
        to_m = lambda t: (axis_angle_rotation(axes[0], t[..., 0])
                          @ axis_angle_rotation(axes[1], t[..., 1])
                          @ axis_angle_rotation(axes[2], t[..., 2]))
        RotationGroup((3, 4, 5), to_matrix=to_m)
    """

    indices: tuple[int, int, int]
    to_matrix: ToMatrix | None = None
    from_matrix: FromMatrix | None = None
    axes: torch.Tensor | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        idx = tuple(int(i) for i in self.indices)
        if len(idx) != 3 or len(set(idx)) != 3:
            raise ValueError(f"indices: expected three distinct indices, got {self.indices!r}")
        object.__setattr__(self, "indices", idx)

    @classmethod
    def from_axes(
        cls, indices: Sequence[int], axes: torch.Tensor | Sequence[Sequence[float]]
    ) -> RotationGroup:
        """Angles through three unit axes ``(3, 3)`` (rows), composed as in the Skeleton:
        ``rot(a1, t1) @ rot(a2, t2) @ rot(a3, t3)``; inverse by :func:`angles_from_matrix`."""
        ax = torch.as_tensor(axes, dtype=torch.float64)
        if ax.shape != (3, 3) or not bool(torch.isfinite(ax).all()):
            raise ValueError(
                f"axes: expected three finite axes, shape (3, 3), got {tuple(ax.shape)}"
            )
        if bool((ax.norm(dim=-1) < 1e-12).any()):
            raise ValueError("axes: zero-length axis")
        ax = ax / ax.norm(dim=-1, keepdim=True)

        def to_matrix(t: torch.Tensor) -> torch.Tensor:
            return euler_matrix(ax, t)

        return cls(tuple(indices), to_matrix=to_matrix, axes=ax)

    def matrix(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., 3) -> (..., 3, 3)``."""
        return so3_exp(x) if self.to_matrix is None else self.to_matrix(x)

    def values(self, R: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
        """``R (..., 3, 3)``, ``reference (..., 3)`` → coordinates ``(..., 3)``."""
        if self.from_matrix is not None:
            return self.from_matrix(R, reference)
        if self.to_matrix is None:
            return _rotvec_from_matrix(R, reference)
        return angles_from_matrix(self.to_matrix, R, reference)


def skeleton_rotation_groups(skeleton, joints: Sequence[str] | None = None) -> list[RotationGroup]:
    """Rotation groups for 3-axis joints of a ``torchmocap.skeleton.Skeleton`` (duck-typed: uses
    ``joint_names``, ``joint_axes``, ``joint_dofs`` and ``rotation_dofs``).

    Args:
        skeleton: the tracking skeleton.
        joints: joint names (each must have exactly 3 axes); default: the root only — the joint
            whose rotation is unlimited and may wrap.
    """
    names = [skeleton.joint_names[0]] if joints is None else list(joints)
    rot = set(skeleton.rotation_dofs)
    out = []
    for name in names:
        j = skeleton.joint_index(name)
        axes = skeleton.joint_axes[j]
        if len(axes) != 3:
            raise ValueError(f"joints: {name!r} has {len(axes)} axes; a rotation group needs 3")
        idx = [i for i in skeleton.joint_dofs(name) if i in rot]
        out.append(RotationGroup.from_axes(idx, axes))
    return out


def _as_groups(groups) -> tuple[RotationGroup, ...]:
    out = []
    for g in groups or ():
        out.append(g if isinstance(g, RotationGroup) else RotationGroup(tuple(g)))
    return tuple(out)


def _check_history(history: torch.Tensor) -> None:
    if not isinstance(history, torch.Tensor) or not history.is_floating_point():
        raise TypeError("history: expected a floating-point torch.Tensor of shape (..., T, D)")
    if history.dim() < 2 or history.shape[-2] < 3 or history.shape[-1] < 1:
        raise ValueError(
            f"history: expected shape (..., T, D) with T >= 3, got {tuple(history.shape)}"
        )
    if not bool(torch.isfinite(history).all()):
        raise ValueError("history: expected finite values, found NaN or inf")


def _check_groups(groups: Sequence[RotationGroup], d: int) -> None:
    seen: set[int] = set()
    for g in groups:
        for i in g.indices:
            if not -d <= i < d:
                raise ValueError(f"rotation_groups: index {i} out of range for D = {d}")
            if i % d in seen:
                raise ValueError(f"rotation_groups: index {i} appears in two groups")
            seen.add(i % d)


def _bound(x: torch.Tensor, lower, upper, name_lo="lower", name_hi="upper") -> torch.Tensor:
    d = x.shape[-1]
    for b, name in ((lower, name_lo), (upper, name_hi)):
        if b is not None:
            t = torch.as_tensor(b, dtype=x.dtype, device=x.device)
            if t.dim() > 1 or (t.dim() == 1 and t.shape[0] != d):
                raise ValueError(f"{name}: expected a scalar or shape ({d},), got {tuple(t.shape)}")
    if lower is not None:
        x = torch.maximum(x, torch.as_tensor(lower, dtype=x.dtype, device=x.device))
    if upper is not None:
        x = torch.minimum(x, torch.as_tensor(upper, dtype=x.dtype, device=x.device))
    return x


def _mode_uv(mode: str, damping: tuple[float, float]) -> tuple[float, float]:
    """Increment extrapolation ``x̂ − x1 = u Δ1 + v Δ2`` of the scalar modes."""
    if mode == "constant_acceleration":
        return 2.0, -1.0
    lam1, lam2 = damping
    return lam1 + lam2, -lam2


def predict_ar3(
    history: torch.Tensor,
    mode: str = "constant_acceleration",
    *,
    damping: tuple[float, float] = (0.8, 0.3),
    rotation_groups: Sequence[RotationGroup | Sequence[int]] = (),
    lower: torch.Tensor | float | None = None,
    upper: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """Predict the next pose from the last three: ``history (..., T, D) -> (..., D)``.

    Args:
        history: chronological poses, ``T ≥ 3`` (the last row is the most recent).
        mode: ``"constant_acceleration"`` or ``"damped"``.
        damping: ``(λ1, λ2)`` of the damped mode (defaults are a heuristic, not the paper's).
        rotation_groups: coordinates composed on SO(3) (see :class:`RotationGroup`; a plain
            triple of indices means a rotation vector).
        lower, upper: limits, scalar or ``(D,)``; the prediction is clamped to them.
    Returns:
        ``(..., D)`` predicted pose.
    """
    _check_history(history)
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    groups = _as_groups(rotation_groups)
    d = history.shape[-1]
    _check_groups(groups, d)
    x3, x2, x1 = history[..., -3:, :].unbind(-2)

    u, v = _mode_uv(mode, damping)
    pred = x1 + u * (x1 - x2) + v * (x2 - x3)

    if groups:
        rc = torch.tensor([[u, v]] * len(groups), dtype=history.dtype, device=history.device)
        pred = pred.clone()
        for gi, g in enumerate(groups):
            idx = list(g.indices)
            R1, R2, R3 = g.matrix(x1[..., idx]), g.matrix(x2[..., idx]), g.matrix(x3[..., idx])
            d1 = so3_log(R2.transpose(-1, -2) @ R1)
            d2 = so3_log(R3.transpose(-1, -2) @ R2)
            dh = rc[gi, 0] * d1 + rc[gi, 1] * d2
            Rh = R1 @ so3_exp(dh)
            pred[..., idx] = g.values(Rh, x1[..., idx]).to(pred.dtype)
    return _bound(pred, lower, upper)


class PosePredictor(torch.nn.Module):
    """Next-pose prediction of a tracker from its last estimates (Pons-Moll §4.3).

    With three or more estimates: :func:`predict_ar3` on the last three, the root rotation
    composed on SO(3) (:func:`skeleton_rotation_groups`), clamped to the joint limits. With two:
    half a constant-velocity step; with one: that estimate.

    Args:
        skeleton: the tracking model (limits, root axes).
        mode: ``"damped"`` (default), ``"constant_acceleration"`` or ``"constant_position"``.
        damping: ``(λ1, λ2)`` of the damped mode.

    ``forward(history (T, D)) -> (D,)``, chronological history (most recent last).
    """

    PREDICTOR_MODES = ("damped", "constant_acceleration", "constant_position")

    def __init__(self, skeleton, mode: str = "damped",
                 damping: Sequence[float] = (0.8, 0.3)) -> None:
        super().__init__()
        if mode not in self.PREDICTOR_MODES:
            raise ValueError(f"mode: expected one of {self.PREDICTOR_MODES}, got {mode!r}")
        damping = tuple(float(x) for x in damping)
        if len(damping) != 2:
            raise ValueError(f"damping: expected two numbers (l1, l2), got {damping!r}")
        self.mode = mode
        self.damping = (0.0, 0.0) if mode == "constant_position" else damping
        self.register_buffer("lower", skeleton.lower.detach().clone())
        self.register_buffer("upper", skeleton.upper.detach().clone())
        root = skeleton.joint_names[0]
        groups = (skeleton_rotation_groups(skeleton, [root])
                  if len(skeleton.joint_axes[0]) == 3 else [])
        self._ar_mode = "constant_acceleration" if mode == "constant_acceleration" else "damped"
        self._groups = _as_groups(groups)

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        if history.dim() != 2 or history.shape[-1] != self.lower.shape[0]:
            raise ValueError(f"history: expected shape (T, {self.lower.shape[0]}), got "
                             f"{tuple(history.shape)}")
        lo, hi = self.lower.to(history.dtype), self.upper.to(history.dtype)
        if history.shape[0] >= 3 and self.mode != "constant_position":
            pred = predict_ar3(history[-3:].double(), self._ar_mode, damping=self.damping,
                               rotation_groups=self._groups).to(history.dtype)
        elif history.shape[0] == 2 and self.mode != "constant_position":
            pred = history[-1] + 0.5 * (history[-1] - history[-2])
        else:
            pred = history[-1].clone()
        return torch.maximum(torch.minimum(pred, hi), lo)

    def extra_repr(self) -> str:
        return f"mode={self.mode!r}, damping={self.damping}"
