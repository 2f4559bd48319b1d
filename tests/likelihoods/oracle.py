"""Test helper: exact capsule silhouettes (every pixel tested against every projected capsule)."""

from __future__ import annotations

import torch

from torchmocap.likelihoods.silhouette import render_capsule_silhouettes


def capsule_masks(body, rig, theta: torch.Tensor) -> torch.Tensor:
    """Masks ``(C, H, W)`` bool of the capsule body at pose ``theta (D,)``."""
    return render_capsule_silhouettes(body, rig, theta)


def surface_point(kin, body, pattern, ep, p: int, i: int):
    """Pattern point ``i`` of pose ``p`` computed one at a time: (capsule, position, normal)."""
    b = int(pattern["bone"][i])
    n = kin.rotations[p, body.parent_index[b]] @ pattern["radial"][i].float()
    a, e = ep[p, b, 0], ep[p, b, 1]
    return b, a + pattern["t"][i].float() * (e - a) + body.radii[b] * n, n


def appearance_loop(kin, body, pattern, rig, imgs, p: int, view_valid=None,
                    min_facing: float = 0.0) -> tuple[float, int]:
    """V_app of pose ``p``, one point and one view at a time: the mean across-view colour
    variance of the points seen by two or more views (a view sees a point inside the image
    whose normal faces it by a cosine above ``min_facing``); returns (value, points counted)."""
    centres = rig.camera_centers()
    ep = body.endpoints(kin)
    variances = []
    for i in range(pattern["bone"].shape[0]):
        _, x, n = surface_point(kin, body, pattern, ep, p, i)
        x, n = x.to(centres.dtype), n.to(centres.dtype)
        cols = []
        for c in range(rig.num_cameras):
            if view_valid is not None and not view_valid[c]:
                continue
            pix, _, vis = rig.project(x[None])
            ray = centres[c] - x
            if vis[c, 0] and float(ray @ n) > min_facing * float(ray.norm()):
                u, v = (pix[c, 0] + 0.5).floor().long().tolist()  # nearest pixel
                cols.append(imgs[c, v, u].double() / 255)
        if len(cols) >= 2:
            variances.append(torch.stack(cols).var(0, unbiased=False).mean())
    return torch.stack(variances).mean().item(), len(variances)
