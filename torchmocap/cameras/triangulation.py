"""Multi-view triangulation of 2D detections: confidence-weighted DLT (what Pose2Sim does).

For a point seen at pixel ``u_c`` in camera ``c`` with projection ``P_c = K_c [R_c | t_c]``, the
direct linear transform stacks the two rows ``w_c (u_c P_c[2] - P_c[0])``,
``w_c (v_c P_c[2] - P_c[1])`` per camera and takes the homogeneous point ``X`` as the right
singular vector of the smallest singular value (Hartley & Zisserman, §12.2). Pixels are first
undistorted (the rig's Brown–Conrady model) and normalised by ``K``, so the rows are those of the
normalised cameras ``[R_c | t_c]`` — better conditioned than raw pixel rows and exact for
distorted lenses. A weight ``w_c = 0`` (missed detection, confidence 0) drops the camera; a
point seen by fewer than two cameras is NaN.

:func:`triangulate_robust` keeps, point by point, only the views that agree (within a pixel
threshold) with the best two-view proposal, as a RANSAC over view pairs: one wrong detection (a
keypoint put on the other leg, a bystander's wrist) no longer drags the point off. Pose2Sim
similarly drops views by their reprojection error before it interpolates and filters.

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

import itertools

import torch
from torch import Tensor

__all__ = ["triangulate_dlt", "triangulate_robust"]


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


def triangulate_robust(pixels: Tensor, weights: Tensor, rig, max_error: float,
                       min_views: int = 2) -> tuple[Tensor, Tensor]:
    """:func:`triangulate_dlt` from the views that agree, per point (RANSAC over view pairs).

    For every point, each pair of views that see it proposes the point triangulated from the
    two; a view is an inlier of a proposal when its reprojection error is at most
    ``max_error``. The proposal with the most inliers wins (ties: the smaller sum of their
    errors), and the point is triangulated from its inliers, confidence-weighted. A wrong
    detection therefore cannot pull the point towards itself and push a good view out, as
    dropping the worst view of an all-view fit does. A point without ``min_views`` views that
    agree is NaN.

    Args:
        pixels: ``(*, C, N, 2)`` pixel coordinates (u, v) per camera and point.
        weights: ``(*, C, N)`` non-negative weights (detection confidences; 0 = not seen).
        rig: the :class:`~torchmocap.cameras.CameraRig` of the detections.
        max_error: largest reprojection error (pixels of ``rig``'s images) of an inlier.
        min_views: inliers a point needs (>= 2).

    Returns:
        ``points (*, N, 3)`` and the weights used ``(*, C, N)`` (0 for a view left out).

    Raises:
        ValueError: what :func:`triangulate_dlt` refuses, or ``max_error`` not a number > 0.

    Example:
        >>> from torchmocap.cameras import make_ring_rig
        >>> rig = make_ring_rig(4).double()
        >>> X = torch.tensor([[0.1, -0.2, 1.0]], dtype=torch.float64)
        >>> pix = rig.project(X)[0].clone()                                  # (4, 1, 2)
        >>> pix[2] += 60.0                                                   # one view wrong
        >>> Y, used = triangulate_robust(pix, torch.ones(4, 1, dtype=X.dtype), rig, 5.0)
        >>> used[:, 0].tolist(), bool(torch.allclose(X, Y, atol=1e-6))
        ([1.0, 1.0, 0.0, 1.0], True)
    """
    if isinstance(max_error, bool) or not isinstance(max_error, (int, float)) \
            or not max_error > 0 or max_error == float("inf"):
        raise ValueError(f"max_error: expected a finite number of pixels > 0, got {max_error!r}")
    triangulate_dlt(pixels, weights, rig, min_views=min_views)  # checks the inputs
    seen = torch.isfinite(pixels).all(-1) & (weights > 0)
    w = torch.where(seen, weights.to(pixels.dtype), torch.zeros_like(pixels[..., 0]))
    uv = pixels.nan_to_num()
    C = rig.num_cameras
    best_in = torch.zeros_like(seen)
    best_n = torch.zeros(seen.shape[:-2] + seen.shape[-1:], dtype=torch.long,
                         device=seen.device)
    best_cost = torch.full(best_n.shape, float("inf"), dtype=pixels.dtype, device=seen.device)
    for a, b in itertools.combinations(range(C), 2):
        pair = torch.zeros(C, 1, dtype=pixels.dtype, device=pixels.device)
        pair[[a, b]] = 1.0
        X = triangulate_dlt(pixels, w * pair, rig)  # (*, N, 3), NaN unless both see it
        err = (rig.project(X.nan_to_num())[0] - uv).norm(dim=-1)  # (*, C, N)
        inl = seen & (err <= max_error) & torch.isfinite(X).all(-1).unsqueeze(-2)
        n = inl.sum(-2)
        cost = torch.where(inl, err, torch.zeros_like(err)).sum(-2)
        better = (n > best_n) | ((n == best_n) & (n > 0) & (cost < best_cost))
        best_in = torch.where(better.unsqueeze(-2), inl, best_in)
        best_n = torch.where(better, n, best_n)
        best_cost = torch.where(better, cost, best_cost)
    used = torch.where(best_in, w, torch.zeros_like(w))
    return triangulate_dlt(pixels, used, rig, min_views=min_views), used
