"""Appearance term V_app (Pons-Moll et al. 2010, eq. 17): colour consistency of the visible surface.

A fixed pattern of body-fixed points (``axial x around`` per capsule, moving rigidly with the
bone) is projected into every view; each point's colour is read where it faces the camera and
lies inside the image. A correct pose sees the same surface point with the same colour in all
views that see it; a wrong pose mixes body and background. ``V_app`` is the mean (over points
seen by at least two views) of the across-view colour variance, in units of the full colour
range squared (so in [0, 0.25]). Self-occlusion by other body parts is not modelled.
Shapes: ``P`` particles, ``C`` views, ``B`` capsules, ``N`` surface points.
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["AppearanceLikelihood", "appearance_energy", "body_surface_pattern"]


def body_surface_pattern(body, axial: int = 4, around: int = 6) -> dict[str, torch.Tensor]:
    """Body-fixed surface pattern of a :class:`~torchmocap.body.CapsuleBody`.

    Returns tensors ``bone (N,)`` (capsule index), ``t (N,)`` position along the axis,
    ``radial (N, 3)`` unit direction in the rest frame of the bone's parent joint.
    """
    sk = body.skeleton
    rest = sk(sk.zero_pose(dtype=torch.float64)).positions
    a = rest[body.parent_index]
    b = rest[body.child_index]
    axis = torch.nn.functional.normalize(b - a, dim=-1)
    helper = torch.where((axis[:, :1].abs() < 0.9), torch.tensor([1.0, 0, 0], dtype=axis.dtype),
                         torch.tensor([0, 1.0, 0], dtype=axis.dtype))
    e1 = torch.nn.functional.normalize(torch.cross(axis, helper, dim=-1), dim=-1)
    e2 = torch.cross(axis, e1, dim=-1)
    t = (torch.arange(axial, dtype=torch.float64) + 0.5) / axial
    phi = torch.arange(around, dtype=torch.float64) * (2 * math.pi / around)
    B = a.shape[0]
    radial = (torch.cos(phi)[None, :, None] * e1[:, None] + torch.sin(phi)[None, :, None]
              * e2[:, None])  # (B, around, 3)
    bone = torch.arange(B).repeat_interleave(axial * around)
    tt = t.repeat_interleave(around).repeat(B)
    rad = radial[:, None].expand(B, axial, around, 3).reshape(-1, 3)
    return {"bone": bone, "t": tt, "radial": rad}


def appearance_energy(kin, body, pattern: dict, rig, images: torch.Tensor,
                      view_valid: torch.Tensor | None = None) -> torch.Tensor:
    """``V_app (P,)`` of poses ``kin`` against colour ``images (C, H, W, 3)`` (uint8 or [0, 1])."""
    if images.dim() != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected shape (C, H, W, 3), got {tuple(images.shape)}")
    dtype = kin.positions.dtype
    ep = body.endpoints(kin)  # (P, B, 2, 3)
    bone, t, radial = pattern["bone"], pattern["t"].to(dtype), pattern["radial"].to(dtype)
    R = kin.rotations[:, body.parent_index[bone]]  # (P, N, 3, 3)
    a, b = ep[:, bone, 0], ep[:, bone, 1]
    n = (R @ radial[..., None])[..., 0]
    pts = a + t[:, None] * (b - a) + body.radii.to(dtype)[bone][:, None] * n  # (P, N, 3)
    pix, _, vis = rig.project(pts)  # (P, C, N, 2), (P, C, N)
    centres = rig.camera_centers().to(dtype)  # (C, 3)
    facing = ((centres[None, :, None] - pts[:, None]) * n[:, None]).sum(-1) > 0
    ok = vis & facing
    if view_valid is not None:
        ok = ok & view_valid.to(ok.device)[None, :, None]
    C, H, W, _ = images.shape
    img = images.to(dtype)
    if images.dtype == torch.uint8:
        img = img / 255.0
    x = pix[..., 0].floor().long().clamp(0, W - 1)
    y = pix[..., 1].floor().long().clamp(0, H - 1)
    flat = img.reshape(C * H * W, 3)
    cam = (torch.arange(C, device=x.device) * (H * W))[None, :, None]
    cols = flat[(cam + y * W + x).reshape(-1)].reshape(*x.shape, 3)  # (P, C, N, 3)
    w = ok.to(dtype)[..., None]
    cnt = w.sum(1)  # (P, N, 1)
    mean = (cols * w).sum(1) / cnt.clamp_min(1)
    var = (((cols - mean[:, None]) ** 2) * w).sum(1).sum(-1, keepdim=True) / cnt.clamp_min(1) / 3
    seen = (cnt >= 2).to(dtype)
    return ((var * seen).sum((1, 2)) / seen.sum((1, 2)).clamp_min(1))


class AppearanceLikelihood(nn.Module):
    """Log-likelihood ``-weight * V_app`` (``lambda_2 = 40`` in Pons-Moll eq. 17)."""

    def __init__(self, body, rig, weight: float = 40.0, axial: int = 4, around: int = 6):
        super().__init__()
        self.body = body
        self.rig = rig
        self.weight = float(weight)
        self.pattern = body_surface_pattern(body, axial, around)

    def energy(self, theta: torch.Tensor, images: torch.Tensor, view_valid=None) -> torch.Tensor:
        kin = self.body.skeleton(theta, check_finite=False)
        return appearance_energy(kin, self.body, self.pattern, self.rig, images, view_valid)

    def forward(self, theta: torch.Tensor, images: torch.Tensor, view_valid=None):
        return -self.weight * self.energy(theta, images, view_valid)
