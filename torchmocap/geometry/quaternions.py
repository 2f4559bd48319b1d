"""Unit quaternions in **w, x, y, z** order (scalar first).

A caller passing x, y, z, w gets a valid-looking, wrong rotation: convert at library boundaries
(scipy uses x, y, z, w). Matrix conversions delegate to kornia (its branch choice by the largest
diagonal term is robust near ``pi``); multiplication, slerp and the atan2 geodesic distance of
Pons-Moll et al. (eq. 19) live here.
"""

from __future__ import annotations

import torch
from kornia.geometry import conversions as _kc

from torchmocap.geometry._checks import check_last_dims

__all__ = [
    "quaternion_multiply",
    "quaternion_conjugate",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "quaternion_to_axis_angle",
    "axis_angle_to_quaternion",
    "quaternion_slerp",
    "quaternion_angle",
    "quaternion_canonical",
    "random_quaternion",
]


def quaternion_multiply(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``q1 ⊗ q2`` of ``(*, 4)`` quaternions (w, x, y, z); broadcasts."""
    check_last_dims(q1, (4,), "q1")
    check_last_dims(q2, (4,), "q2")
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def quaternion_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate ``(w, -x, -y, -z)``; the inverse of a unit quaternion."""
    check_last_dims(q, (4,), "q")
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quaternion_canonical(q: torch.Tensor) -> torch.Tensor:
    """Representative with ``w >= 0`` of the same rotation (``q`` and ``-q`` are one rotation)."""
    check_last_dims(q, (4,), "q")
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(*, 4)`` (w, x, y, z) to rotation matrix ``(*, 3, 3)``."""
    check_last_dims(q, (4,), "q")
    return _kc.quaternion_to_rotation_matrix(q)


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``(*, 3, 3)`` to unit quaternion ``(*, 4)`` with ``w >= 0``."""
    check_last_dims(R, (3, 3), "R")
    shape = R.shape[:-2]
    q = _kc.rotation_matrix_to_quaternion(R.reshape(-1, 3, 3))
    q = torch.nn.functional.normalize(q, dim=-1)
    return quaternion_canonical(q).reshape(*shape, 4)


def quaternion_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(*, 4)`` to rotation vector ``(*, 3)`` with angle in [0, pi].

    ``angle = 2 atan2(|v|, |w|)``; the series ``2/|w|`` is used for tiny ``|v|``.
    """
    check_last_dims(q, (4,), "q")
    q = quaternion_canonical(q)
    w, v = q[..., :1], q[..., 1:]
    n2 = (v * v).sum(-1, keepdim=True)
    small = n2 < 1e-12
    n = torch.where(small, torch.ones_like(n2), n2).sqrt()
    scale = torch.where(small, 2.0 / w.clamp_min(1e-30) * (1 - n2 / (3 * w * w).clamp_min(1e-30)),
                        2 * torch.atan2(n, w) / n)
    return v * scale


def axis_angle_to_quaternion(w: torch.Tensor) -> torch.Tensor:
    """Rotation vector ``(*, 3)`` to unit quaternion ``(*, 4)``; exact near zero."""
    check_last_dims(w, (3,), "w")
    t2 = (w * w).sum(-1, keepdim=True)
    small = t2 < 1e-8
    t = torch.where(small, torch.ones_like(t2), t2).sqrt()
    half_sinc = torch.where(small, 0.5 - t2 / 48, torch.sin(0.5 * t) / t)
    cos_half = torch.where(small, 1 - t2 / 8, torch.cos(0.5 * t))
    return torch.cat([cos_half, w * half_sinc], dim=-1)


def quaternion_angle(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (radians) between rotations, Pons-Moll eq. 19 in the atan2 form.

    ``d = 2 atan2(||r_xyz||, |r_w|)`` with ``r = q1* ⊗ q2``. Accurate to ~1e-5 degrees in float32,
    smooth at zero (the printed ``2 arccos|<q1, q2>|`` needs clamping and has infinite slope there).
    """
    r = quaternion_multiply(quaternion_conjugate(q1), q2)
    return 2 * torch.atan2(r[..., 1:].norm(dim=-1), r[..., 0].abs())


def quaternion_slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Spherical linear interpolation along the shorter arc; ``t`` broadcasts against ``(*)``.

    Falls back to normalised linear interpolation when the quaternions nearly coincide.
    """
    check_last_dims(q0, (4,), "q0")
    check_last_dims(q1, (4,), "q1")
    t = torch.as_tensor(t, dtype=q0.dtype, device=q0.device)
    if t.dim() == 0 or t.shape[-1:] != (1,):
        t = t[..., None]
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    # angle via atan2 of the chord lengths: stable at both ends
    chord_minus = (q0 - q1).norm(dim=-1, keepdim=True)
    chord_plus = (q0 + q1).norm(dim=-1, keepdim=True)
    omega = 2 * torch.atan2(chord_minus, chord_plus)
    so = torch.sin(omega)
    near = so < 1e-6
    so_safe = torch.where(near, torch.ones_like(so), so)
    a = torch.where(near, 1 - t, torch.sin((1 - t) * omega) / so_safe)
    b = torch.where(near, t, torch.sin(t * omega) / so_safe)
    out = a * q0 + b * q1
    return torch.nn.functional.normalize(out, dim=-1)


def random_quaternion(
    n: int | tuple[int, ...],
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Uniform random unit quaternions ``(*n, 4)`` with ``w >= 0`` (normalised 4-D Gaussians)."""
    shape = (n,) if isinstance(n, int) else tuple(n)
    gen_device = generator.device if generator is not None else (device or "cpu")
    g = torch.randn(*shape, 4, generator=generator, dtype=torch.float64, device=gen_device)
    g = torch.nn.functional.normalize(g, dim=-1)
    return quaternion_canonical(g).to(dtype=dtype, device=device or gen_device)


