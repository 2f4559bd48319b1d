"""Exact decomposition of a rotation into angles about 1-3 given orthonormal axes.

A joint of a motion file rotates as ``L = rot(a1, t1) @ rot(a2, t2) @ rot(a3, t3)`` about its
ordered axes ``a_k`` (BVH channel order, ASF ``C M C^-1``). These helpers go back from ``L`` to
the angles ``t``: exact (to rounding) for any ``L`` when the joint has 3 orthonormal axes, and for
``L`` in the joint's reachable set when it has 1 or 2 (otherwise the nearest angles in the
Euler sense: a projection, used after slerp resampling of 2-DoF joints).
"""

from __future__ import annotations

import torch

__all__ = ["angles_to_matrix", "matrix_to_angles"]


def angles_to_matrix(angles: torch.Tensor, axes: torch.Tensor) -> torch.Tensor:
    """Rotation ``rot(a1, t1) @ ... @ rot(ak, tk)``.

    Args:
        angles: ``(*, k)`` radians.
        axes: ``(k, 3)`` unit axes, ``k`` in 0..3.

    Returns:
        ``(*, 3, 3)``; the identity when ``k == 0``.
    """
    from torchmocap.geometry import axis_angle_rotation

    batch = angles.shape[:-1]
    R = torch.eye(3, dtype=angles.dtype, device=angles.device).expand(*batch, 3, 3)
    axes = axes.to(dtype=angles.dtype, device=angles.device)
    for k in range(axes.shape[0]):
        R = R @ axis_angle_rotation(axes[k].expand(*batch, 3), angles[..., k])
    return R


def _check_orthonormal(axes: torch.Tensor) -> None:
    k = axes.shape[0]
    gram = axes @ axes.transpose(0, 1)
    if float((gram - torch.eye(k, dtype=axes.dtype)).abs().max()) > 1e-5:
        raise ValueError(
            f"axes: angle decomposition needs orthonormal joint axes, got {axes.tolist()}"
        )


def matrix_to_angles(R: torch.Tensor, axes: torch.Tensor) -> torch.Tensor:
    """Angles ``(*, k)`` with ``angles_to_matrix(angles, axes) == R``.

    Args:
        R: ``(*, 3, 3)`` rotations.
        axes: ``(k, 3)`` orthonormal unit axes (``k`` in 0..3); for ``k == 3`` the first and
            last axis must differ (Tait-Bryan order, as in every BVH/ASF joint).

    Returns:
        ``(*, k)`` radians; in a gimbal-locked pose (middle angle ``±pi/2``) the last angle
        is set to 0 and the first absorbs the rest, which still reproduces ``R`` exactly.

    Example:
        >>> ax = torch.eye(3)[[2, 0, 1]]  # BVH "Zrotation Xrotation Yrotation"
        >>> R = angles_to_matrix(torch.tensor([0.1, 0.2, 0.3]), ax)
        >>> matrix_to_angles(R, ax)
        tensor([0.1000, 0.2000, 0.3000])
    """
    axes = axes.to(dtype=R.dtype, device=R.device)
    k = axes.shape[0]
    batch = R.shape[:-2]
    if k == 0:
        return R.new_zeros(*batch, 0)
    _check_orthonormal(axes)
    if k == 1:
        a = axes[0]
        v = 0.5 * torch.stack(
            [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
            -1,
        )
        c = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
        return torch.atan2((v * a).sum(-1), c)[..., None]
    if k == 2:
        B = torch.stack([axes[0], axes[1], torch.linalg.cross(axes[0], axes[1])], -1)
        Rp = B.transpose(0, 1) @ R @ B  # = Rx(t1) Ry(t2) for reachable R
        t1 = torch.atan2(Rp[..., 2, 1], Rp[..., 1, 1])
        t2 = torch.atan2(Rp[..., 0, 2], Rp[..., 0, 0])
        return torch.stack([t1, t2], -1)
    if float(torch.linalg.cross(axes[0], axes[2]).norm()) < 0.5:
        raise ValueError("axes: first and last axis coincide (proper Euler order unsupported)")
    B = axes.transpose(0, 1)  # columns a1, a2, a3
    s = torch.linalg.det(B)  # +-1: a reflection flips the angle signs
    Rp = B.transpose(0, 1) @ R @ B  # = Rx(s t1) Ry(s t2) Rz(s t3)
    cb = torch.sqrt(Rp[..., 0, 0] ** 2 + Rp[..., 0, 1] ** 2)
    beta = torch.atan2(Rp[..., 0, 2], cb)
    locked = cb < 1e-9
    alpha = torch.where(
        locked,
        torch.atan2(Rp[..., 2, 1], Rp[..., 1, 1]),
        torch.atan2(-Rp[..., 1, 2], Rp[..., 2, 2]),
    )
    gamma = torch.where(locked, torch.zeros_like(beta), torch.atan2(-Rp[..., 0, 1], Rp[..., 0, 0]))
    return torch.stack([alpha, beta, gamma], -1) * s
