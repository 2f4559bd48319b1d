"""Twists and rigid motions (Pons-Moll et al. 2010, eqs. 1-2).

A twist ``xi = (v, w)`` ``(*, 6)`` has linear part ``v`` and angular part ``w``; a revolute joint
with unit axis ``w`` through point ``q`` has ``v = -w x q``. ``se3_exp(xi * theta)`` is the rigid
motion ``(*, 4, 4)`` of rotating by ``theta`` about that axis (product-of-exponentials kinematics).
"""

from __future__ import annotations

import torch
from kornia.geometry.liegroup import Se3

from torchmocap.geometry._checks import check_last_dims

__all__ = ["revolute_twist", "se3_exp", "transform_points", "make_transform"]


def revolute_twist(axis: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """Twist ``(*, 6)`` = ``(-axis x point, axis)`` of a revolute joint."""
    check_last_dims(axis, (3,), "axis")
    check_last_dims(point, (3,), "point")
    axis, point = torch.broadcast_tensors(axis, point)
    return torch.cat([-torch.cross(axis, point, dim=-1), axis], dim=-1)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Exponential of a twist ``(*, 6)`` (``v``, ``w``; ``theta`` folded in) to ``(*, 4, 4)``.

    ``exp = [[R, V v], [0, 1]]`` with ``R = exp(w^)``; delegates to kornia's ``Se3.exp`` (same
    ``(v, w)`` ordering, series branches near zero).
    """
    check_last_dims(xi, (6,), "xi")
    shape = xi.shape[:-1]
    return Se3.exp(xi.reshape(-1, 6)).matrix().reshape(*shape, 4, 4)


def make_transform(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Homogeneous transforms ``(*, 4, 4)`` from ``R`` ``(*, 3, 3)`` and ``t`` ``(*, 3)``."""
    check_last_dims(R, (3, 3), "R")
    check_last_dims(t, (3,), "t")
    R, t = torch.broadcast_tensors(R, t[..., None])[0], t
    top = torch.cat([R, t[..., None]], dim=-1)
    bottom = torch.zeros(*R.shape[:-2], 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def transform_points(T: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Apply ``(*, 4, 4)`` transforms to points ``(*, 3)`` (broadcasting)."""
    check_last_dims(T, (4, 4), "T")
    check_last_dims(x, (3,), "x")
    return (T[..., :3, :3] @ x[..., None])[..., 0] + T[..., :3, 3]
