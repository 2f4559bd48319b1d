"""Rotation coordinates of a pose vector: groups of three coordinates that parameterise a
rotation (a 3-axis joint's Euler-type angles, or a rotation vector), mapped to matrices and back
on the branch nearest a reference — what prediction, averaging and smoothing compose on SO(3)
instead of treating angles as plain numbers.

Shapes: ``D`` pose coordinates, ``G`` rotation groups.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from torchmocap.geometry import axis_angle_rotation, so3_exp, so3_log

__all__ = ["RotationGroup", "angles_from_matrix", "as_groups", "euler_matrix",
           "skeleton_rotation_groups"]

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


def as_groups(groups) -> tuple[RotationGroup, ...]:
    out = []
    for g in groups or ():
        out.append(g if isinstance(g, RotationGroup) else RotationGroup(tuple(g)))
    return tuple(out)
