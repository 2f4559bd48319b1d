"""Rotations in SO(3): exp/log maps, skew matrices, geodesic angles and random rotations.

Conventions: rotation vectors (axis * angle, radians) have shape ``(*, 3)``; rotation matrices
``(*, 3, 3)`` act on column vectors. Rodrigues' formula uses Taylor branches near zero so values
and gradients stay finite and exact at ``0`` and near ``pi``.
"""

from __future__ import annotations

import torch
from kornia.geometry import conversions as _kc

from torchmocap.geometry._checks import check_last_dims

__all__ = [
    "hat",
    "vee",
    "so3_exp",
    "so3_log",
    "axis_angle_rotation",
    "geodesic_angle",
    "random_rotation_matrix",
    "rotation_mean",
]


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix of ``w`` so that ``hat(w) @ v == cross(w, v)``.

    Args:
        w: ``(*, 3)``.
    Returns:
        ``(*, 3, 3)``.
    """
    check_last_dims(w, (3,), "w")
    x, y, z = w.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*w.shape[:-1], 3, 3)


def vee(m: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat`, using the antisymmetric part of ``m``: ``(*, 3, 3) -> (*, 3)``."""
    check_last_dims(m, (3, 3), "m")
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        dim=-1,
    )


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Exponential map: rotation vector ``(*, 3)`` to rotation matrix ``(*, 3, 3)``.

    Delegates to kornia's Rodrigues implementation, whose small-angle branch is exact to float64
    precision with finite gradients at zero (checked in ``tests/geometry``).

    Example:
        >>> so3_exp(torch.zeros(2, 3)).shape
        torch.Size([2, 3, 3])
    """
    check_last_dims(w, (3,), "w")
    shape = w.shape[:-1]
    return _kc.axis_angle_to_rotation_matrix(w.reshape(-1, 3)).reshape(*shape, 3, 3)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Logarithm map: rotation matrix ``(*, 3, 3)`` to rotation vector ``(*, 3)``, angle in [0, pi].

    Goes through a unit quaternion (kornia's branch-robust conversion, then an ``atan2`` angle), so
    it is accurate near ``0`` and near ``pi``.
    """
    check_last_dims(R, (3, 3), "R")
    from torchmocap.geometry.quaternions import matrix_to_quaternion, quaternion_to_axis_angle

    return quaternion_to_axis_angle(matrix_to_quaternion(R))


def axis_angle_rotation(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation about unit ``axis`` ``(*, 3)`` by ``angle`` ``(*)`` radians: ``(*, 3, 3)``.

    Cheaper than :func:`so3_exp` when the axis is already unit-norm (no branch needed).
    """
    check_last_dims(axis, (3,), "axis")
    K = hat(axis)
    s = torch.sin(angle)[..., None, None]
    c = torch.cos(angle)[..., None, None]
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device)
    return eye + s * K + (1 - c) * (K @ K)


def geodesic_angle(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Angle (radians, in [0, pi]) of the relative rotation ``R1^T R2``: ``(*, 3, 3) -> (*)``.

    Uses ``atan2(||vee-part||, (tr - 1)/2)``, accurate near 0 and pi, unlike ``arccos``.
    """
    check_last_dims(R1, (3, 3), "R1")
    check_last_dims(R2, (3, 3), "R2")
    M = R1.transpose(-1, -2) @ R2
    v = vee(M)
    s = (v * v).sum(-1).clamp_min(1e-30).sqrt()  # finite gradient at zero angle
    c = 0.5 * (M.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
    return torch.atan2(s, c)


def random_rotation_matrix(
    n: int | tuple[int, ...],
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Uniform (Haar) random rotations, ``(*n, 3, 3)``, from normalised Gaussian quaternions."""
    from torchmocap.geometry.quaternions import quaternion_to_matrix, random_quaternion

    return quaternion_to_matrix(random_quaternion(n, generator, dtype, device))




def rotation_mean(R: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Weighted chordal mean of rotations over the first dim: ``(P, *, 3, 3) -> (*, 3, 3)``.

    ``proj_SO(3)(Σ_i w_i R_i)`` (the closest rotation to the weighted arithmetic mean, by SVD with
    the determinant fixed), computed in float64. ``weights (P,)`` are normalised here (default
    uniform). Averaging Euler angles instead fails at their seams and near gimbal lock.

    Example:
        >>> R = so3_exp(torch.tensor([[0.0, 0.0, 0.1], [0.0, 0.0, 0.3]]))
        >>> bool(torch.allclose(rotation_mean(R), so3_exp(torch.tensor([0.0, 0.0, 0.2])),
        ...                     atol=1e-6))
        True
    """
    check_last_dims(R, (3, 3), "R")
    P = R.shape[0]
    if weights is None:
        weights = torch.ones(P, dtype=torch.float64, device=R.device)
    if weights.shape != (P,):
        raise ValueError(f"weights: expected shape ({P},), got {tuple(weights.shape)}")
    w = weights.to(torch.float64)
    if not bool(torch.isfinite(w).all()) or bool((w < 0).any()) or not float(w.sum()) > 0:
        raise ValueError("weights: expected finite values >= 0 with a positive sum")
    w = w / w.sum()
    M = (w.reshape(P, *([1] * (R.dim() - 1))) * R.to(torch.float64)).sum(0)
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.linalg.det(U @ Vh))
    fix = torch.ones(*M.shape[:-2], 3, dtype=M.dtype, device=M.device)
    fix[..., 2] = torch.where(d == 0, torch.ones_like(d), d)
    return ((U * fix[..., None, :]) @ Vh).to(R.dtype)
