"""One depth camera (Hauberg & Pedersen's stereo rig): point clouds of the visible body surface.

The body is z-buffered in the depth camera; every covered pixel is back-projected with its
depth (a point on the visible triangle), then corrupted: random dropouts, disc-shaped holes and
stereo-like depth noise along the viewing ray whose std grows with depth squared
(``σ(z) = noise_std · z²``, ``noise_std`` in metres at 1 m). Frames have different point
counts: they are stored padded ``(T, N, 3)`` with ``counts (T,)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmocap.data.depth import DepthData
from torchmocap.data.synthetic.render import rasterize_zbuffer
from torchmocap.data.synthetic.silhouettes import paint_ellipses

__all__ = ["make_depth_camera", "synthesize_depth"]


def make_depth_camera(position, target, image_size, fov_deg: float):
    """A distortion-free one-camera rig at ``position`` looking at ``target`` (Z-up world)."""
    from torchmocap.cameras import CameraRig, look_at

    eye = torch.tensor([list(position)], dtype=torch.float64)
    tgt = torch.tensor([list(target)], dtype=torch.float64)
    R, t = look_at(eye, tgt)
    w, h = int(image_size[0]), int(image_size[1])
    f = 0.5 * w / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]]],
                     dtype=torch.float64)
    return CameraRig(K, R, t, (w, h), None, ["depth0"])


def synthesize_depth(vertices: Tensor, faces: Tensor, camera, generator: torch.Generator,
                     noise_std: float = 0.0, hole_prob: float = 0.0, holes: float = 0.0,
                     hole_radius: tuple[float, float] = (2.0, 5.0), max_points: int = 0
                     ) -> DepthData:
    """Visible-surface point clouds of posed meshes.

    Args:
        vertices: ``(T, V, 3)`` posed mesh vertices (world, m).
        faces: ``(F, 3)``.
        camera: one-camera :class:`~torchmocap.cameras.CameraRig` (distortion-free).
        generator: randomness for noise, dropouts, holes and subsampling.
        noise_std: depth noise std (m) at 1 m; scales with depth².
        hole_prob: fraction of pixels dropped independently.
        holes: mean number (Poisson) of missing discs per frame.
        hole_radius: disc radius range (px).
        max_points: keep at most this many points per frame (random subset); 0 = all.

    Returns:
        :class:`DepthData`.
    """
    from torchmocap.data.synthetic.silhouettes import _poisson

    if vertices.dim() != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices: expected shape (T, V, 3), got {tuple(vertices.shape)}")
    if camera.num_cameras != 1:
        raise ValueError(f"camera: expected a one-camera rig, got {camera.num_cameras} cameras")
    if camera.has_distortion:
        raise ValueError("camera: the depth camera must be distortion-free")
    T = vertices.shape[0]
    W, H = int(camera.image_size[0, 0]), int(camera.image_size[0, 1])
    dt = vertices.dtype
    pix, z, _ = camera.project(vertices)  # (T, 1, V, 2)
    zb = rasterize_zbuffer(pix[:, 0], z[:, 0], faces, W, H)
    keep = zb.mask.clone()
    if hole_prob > 0:
        u = torch.rand(keep.shape, generator=generator, dtype=torch.float64).to(keep.device)
        keep &= u >= hole_prob
    counts = _poisson(holes, T, generator)
    K = int(counts.sum())
    g = torch.rand(K, 3, generator=generator, dtype=torch.float64)
    if K:
        lo, hi = hole_radius
        r = lo + (hi - lo) * g[:, 2]
        paint_ellipses(keep, torch.repeat_interleave(torch.arange(T), counts), g[:, 0] * (W - 1),
                       g[:, 1] * (H - 1), r, r, torch.zeros(K, dtype=torch.float64), False)
    idx = keep.nonzero()  # (N, 3): t, y, x (sorted by t)
    depth = zb.depth[idx[:, 0], idx[:, 1], idx[:, 2]]
    if noise_std > 0:
        eps = torch.randn(depth.shape, generator=generator, dtype=torch.float64).to(depth)
        depth = depth + noise_std * depth * depth * eps
    Kinv = torch.linalg.inv(camera.K[0].to(dt))
    uv1 = torch.stack([idx[:, 2].to(dt), idx[:, 1].to(dt), torch.ones_like(depth)], -1)
    xc = depth[:, None] * (uv1 @ Kinv.T)
    R, t = camera.R[0].to(dt), camera.t[0].to(dt)
    pts = (xc - t) @ R  # R^T (x - t)
    n = torch.bincount(idx[:, 0], minlength=T)
    if max_points > 0 and bool((n > max_points).any()):
        # random subset: sort by (frame, random key) and keep the first max_points of each frame
        key = torch.rand(pts.shape[0], generator=generator, dtype=torch.float64).to(pts.device)
        order = torch.argsort(idx[:, 0].double() * 2 + key)
        pts, frame = pts[order], idx[order, 0]
        start = torch.cumsum(n, 0) - n
        rank = torch.arange(pts.shape[0], device=pts.device) - start[frame]
        sel = rank < max_points
        pts, frame = pts[sel], frame[sel]
        n = n.clamp(max=max_points)
    else:
        frame = idx[:, 0]
    N = int(n.max()) if T else 0
    start = torch.cumsum(n, 0) - n
    slot = torch.arange(pts.shape[0], device=pts.device) - start[frame]
    out = torch.zeros(T, N, 3, dtype=dt, device=pts.device)
    out[frame, slot] = pts
    return DepthData(out, n, camera)
