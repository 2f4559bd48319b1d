"""Test helper: exact capsule silhouettes (every pixel tested against every projected capsule)."""

from __future__ import annotations

import torch

from torchmocap.likelihoods.silhouette import _coverage_margin, project_capsules


def capsule_masks(body, rig, theta: torch.Tensor) -> torch.Tensor:
    """Masks ``(C, H, W)`` bool of the capsule body at pose ``theta (D,)``."""
    ep = body.endpoints(body.skeleton(theta[None]))
    ends, rpx, front = project_capsules(ep, body.radii, rig)
    W, H = (int(v) for v in rig.image_size[0])
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    q = torch.stack([xs + 0.5, ys + 0.5], -1).reshape(1, -1, 2).to(ep.dtype)
    q = q.expand(ends.shape[1], -1, -1)
    rpx = torch.where(front[..., None], rpx, torch.full_like(rpx, -1e3))
    return (_coverage_margin(q, ends, rpx, smooth=False) > 0)[0].reshape(-1, H, W)
