"""Multi-view triangulation of 2D detections: confidence-weighted DLT (what Pose2Sim does).

For a point seen at pixel ``u_c`` in camera ``c`` with projection ``P_c = K_c [R_c | t_c]``, the
direct linear transform stacks the two rows ``w_c (u_c P_c[2] - P_c[0])``,
``w_c (v_c P_c[2] - P_c[1])`` per camera and takes the homogeneous point ``X`` as the right
singular vector of the smallest singular value (Hartley & Zisserman, §12.2). Pixels are first
undistorted (the rig's Brown–Conrady model) and normalised by ``K``, so the rows are those of the
normalised cameras ``[R_c | t_c]`` — better conditioned than raw pixel rows and exact for
distorted lenses. A weight ``w_c = 0`` (missed detection, confidence 0) drops the camera; a
point seen by fewer than two cameras is NaN.

Shapes: ``C`` cameras, ``N`` points (keypoints), ``*`` leading dims (frames).

Example:
    >>> from torchmocap.cameras import make_ring_rig
    >>> rig = make_ring_rig(4).double()
    >>> X = torch.tensor([[0.1, -0.2, 1.0], [0.0, 0.3, 1.5]], dtype=torch.float64)
    >>> pix = rig.project(X)[0]                                  # (C, N, 2)
    >>> Y = triangulate_dlt(pix, torch.ones(4, 2, dtype=torch.float64), rig)
    >>> bool(torch.allclose(X, Y, atol=1e-6))
    True
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["triangulate_dlt"]


def triangulate_dlt(pixels: Tensor, weights: Tensor, rig, undistort: bool = True,
                    min_views: int = 2) -> Tensor:
    """Confidence-weighted DLT triangulation of per-camera detections.

    Args:
        pixels: ``(*, C, N, 2)`` pixel coordinates (u, v) per camera and point.
        weights: ``(*, C, N)`` non-negative weights (detection confidences; 0 = not seen).
        rig: the :class:`~torchmocap.cameras.CameraRig` of the detections (``C`` cameras).
        undistort: remove the rig's lens distortion from the pixels first.
        min_views: points with fewer cameras of positive weight are NaN.

    Returns:
        ``(*, N, 3)`` world points (NaN where fewer than ``min_views`` cameras see the point).

    Raises:
        ValueError: shapes that do not match the rig, negative or non-finite weights.
    """
    C = rig.num_cameras
    if pixels.dim() < 3 or pixels.shape[-1] != 2 or pixels.shape[-3] != C:
        raise ValueError(f"pixels: expected shape (*, {C}, N, 2), got {tuple(pixels.shape)}")
    if weights.shape != pixels.shape[:-1]:
        raise ValueError(f"weights: expected shape {tuple(pixels.shape[:-1])}, got "
                         f"{tuple(weights.shape)}")
    if isinstance(min_views, bool) or not isinstance(min_views, int) or min_views < 2:
        raise ValueError(f"min_views: expected an int >= 2, got {min_views!r}")
    w = weights.to(pixels.dtype)
    if not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
        raise ValueError("weights: expected finite values >= 0")
    finite = torch.isfinite(pixels).all(-1)
    w = torch.where(finite, w, torch.zeros_like(w))
    uv = torch.where(finite[..., None], pixels, torch.zeros_like(pixels))
    # normalised image coordinates: undistorted rays through the pixels, divided by depth
    _, d = rig.backproject(uv, undistort=undistort)  # (*, C, N, 3) world directions
    R, t = rig.R.to(pixels.dtype), rig.t.to(pixels.dtype)
    dc = torch.einsum("cij,...cnj->...cni", R, d)  # camera-frame directions
    xy = dc[..., :2] / dc[..., 2:3].clamp_min(1e-12)
    P = torch.cat([R, t[:, :, None]], -1)  # (C, 3, 4) normalised cameras
    P = P.expand(*pixels.shape[:-3], pixels.shape[-2], C, 3, 4) \
        if pixels.dim() > 3 else P.expand(pixels.shape[-2], C, 3, 4)
    xy_n = xy.movedim(-3, -2)  # (*, N, C, 2)
    w_n = w.movedim(-2, -1)  # (*, N, C)
    rows_x = xy_n[..., 0:1] * P[..., 2, :] - P[..., 0, :]
    rows_y = xy_n[..., 1:2] * P[..., 2, :] - P[..., 1, :]
    A = torch.cat([rows_x * w_n[..., None], rows_y * w_n[..., None]], -2)  # (*, N, 2C, 4)
    # scale rows of each problem to unit max weight (weights only matter relatively)
    A = A / w_n.amax(-1).clamp_min(1e-30)[..., None, None]
    _, _, Vh = torch.linalg.svd(A.to(torch.float64), full_matrices=False)
    X = Vh[..., -1, :]
    pts = (X[..., :3] / X[..., 3:4]).to(pixels.dtype)
    enough = (w_n > 0).sum(-1) >= min_views
    return torch.where(enough[..., None], pts, torch.full_like(pts, float("nan")))
