"""Scores against a view's own 2D detections: reprojection error and PCK, and the
leave-one-camera-out protocol (REFERENCE §11).

A reconstruction ``points3d (T, K, 3)`` is projected into one camera (lens distortion included)
and compared with that camera's detections ``(T, K, 3)`` = (u, v, confidence). Only keypoints
detected with a confidence above ``min_confidence`` are compared; a detected keypoint without a
3D point (NaN: not reconstructed) is counted as missing, not scored. PCK@α is the fraction of
compared keypoints within ``α h_t`` pixels of the detection, ``h_t`` the height of the box
around frame ``t``'s compared detections in that view (frames with fewer than two of them have
no box and take no part in PCK). Held out from the reconstruction, the view's detections are an
independent check; they are noisy themselves, so the score has a floor, and methods are
compared on the same frames, keypoints and threshold.

Shapes: ``T`` frames, ``K`` keypoints, ``C`` cameras.

Example:
    >>> from torchmocap.cameras import make_ring_rig
    >>> rig = make_ring_rig(1).double()
    >>> X = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.5]]], dtype=torch.float64)
    >>> det = torch.cat([rig.project(X)[0][:, 0] + 3.0, torch.ones(1, 2, 1)], -1)
    >>> round(reprojection_scores(X, det, rig).median_px, 3)
    4.243
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["ReprojectionScores", "leave_one_camera_out", "reprojection_scores"]


@dataclass
class ReprojectionScores:
    """Reprojection scores of a reconstruction in one view.

    Attributes:
        median_px, mean_px: median (the middle values' mean for an even count) and mean pixel
            error over the compared keypoints (NaN when none).
        pck_05, pck_10: fractions of the compared keypoints (in frames with a box) within 5 %
            and 10 % of the box height.
        num_compared: keypoints compared (detected above the threshold, with a 3D point).
        num_missing: keypoints detected above the threshold without a 3D point.
        errors_px: ``(T, K)`` pixel errors, NaN where not compared.
        box_height_px: ``(T,)`` height of the box of each frame's compared detections (NaN
            with fewer than two).
        frame_median_px: ``(T,)`` median error per frame (NaN without compared keypoints).
        frame_count: ``(T,)`` compared keypoints per frame.
    """

    median_px: float
    mean_px: float
    pck_05: float
    pck_10: float
    num_compared: int
    num_missing: int
    errors_px: torch.Tensor
    box_height_px: torch.Tensor
    frame_median_px: torch.Tensor
    frame_count: torch.Tensor

    def summary(self) -> dict[str, float]:
        """The scalar scores as a plain dict (for ``metrics.json``)."""
        return {"median_px": self.median_px, "mean_px": self.mean_px, "pck_05": self.pck_05,
                "pck_10": self.pck_10, "num_compared": self.num_compared,
                "num_missing": self.num_missing}


def reprojection_scores(points3d: torch.Tensor, detections: torch.Tensor, rig,
                        min_confidence: float = 0.0) -> ReprojectionScores:
    """Reprojection error and PCK of ``points3d`` against one view's detections.

    Args:
        points3d: ``(T, K, 3)`` world points (metres), NaN where not reconstructed.
        detections: ``(T, K, 3)`` the view's (u, v, confidence) in pixels (confidence 0 =
            missed).
        rig: a :class:`~torchmocap.cameras.CameraRig` of that one camera.
        min_confidence: detections with a confidence above this are compared.

    Returns:
        :class:`ReprojectionScores`.

    Raises:
        ValueError: shapes that do not match, a rig of several cameras, a threshold outside
            ``[0, 1)``, negative confidences.
    """
    if not isinstance(points3d, torch.Tensor) or points3d.dim() != 3 or points3d.shape[-1] != 3:
        shape = tuple(points3d.shape) if isinstance(points3d, torch.Tensor) else type(points3d)
        raise ValueError(f"points3d: expected shape (T, K, 3), got {shape}")
    T, K, _ = points3d.shape
    if not isinstance(detections, torch.Tensor) or detections.shape != (T, K, 3):
        shape = (tuple(detections.shape) if isinstance(detections, torch.Tensor)
                 else type(detections))
        raise ValueError(f"detections: expected shape ({T}, {K}, 3) (u, v, confidence), got "
                         f"{shape}")
    if rig.num_cameras != 1:
        raise ValueError(f"rig: expected the one camera of the detections, got "
                         f"{rig.num_cameras} cameras (use rig.subset([c]))")
    if isinstance(min_confidence, bool) or not (
            isinstance(min_confidence, (int, float)) and 0 <= min_confidence < 1):
        raise ValueError(f"min_confidence: expected a number in [0, 1), got {min_confidence!r}")
    dt = torch.promote_types(points3d.dtype, torch.float32)
    X = points3d.to(dt)
    det = detections.to(device=X.device, dtype=dt)
    conf = det[..., 2]
    if bool((conf < 0).any()):
        raise ValueError("detections: confidences must be >= 0")
    detected = (conf > min_confidence) & torch.isfinite(det[..., :2]).all(-1)
    have = torch.isfinite(X).all(-1)
    compared = detected & have
    pix = rig.project(torch.where(have[..., None], X, torch.zeros_like(X)))[0][:, 0]
    err = (pix - det[..., :2]).norm(dim=-1)
    err = torch.where(compared, err, torch.full_like(err, float("nan")))
    v = torch.where(compared, det[..., 1], torch.full_like(err, float("nan")))
    count = compared.sum(-1)
    height = torch.where(count >= 2, v.nan_to_num(-float("inf")).amax(-1)
                         - v.nan_to_num(float("inf")).amin(-1), torch.full_like(err[:, 0],
                                                                                float("nan")))
    boxed = compared & (count >= 2)[:, None]
    e = err[compared]
    n = int(compared.sum())

    def pck(alpha: float) -> float:
        if not bool(boxed.any()):
            return float("nan")
        return float((err[boxed] <= (alpha * height[:, None].expand_as(err))[boxed]).double()
                     .mean())

    return ReprojectionScores(
        median_px=float(e.quantile(0.5)) if n else float("nan"),
        mean_px=float(e.mean()) if n else float("nan"),
        pck_05=pck(0.05), pck_10=pck(0.10), num_compared=n,
        num_missing=int((detected & ~have).sum()), errors_px=err, box_height_px=height,
        frame_median_px=err.nanquantile(0.5, dim=-1), frame_count=count)


def leave_one_camera_out(detections: torch.Tensor, rig, min_confidence: float = 0.0,
                         triangulate=None) -> list[ReprojectionScores]:
    """Reconstruct from all cameras but one and score in the one left out, for every camera.

    Args:
        detections: ``(T, C, K, 3)`` every view's (u, v, confidence).
        rig: the :class:`~torchmocap.cameras.CameraRig` of the ``C >= 3`` views.
        min_confidence: threshold of the compared detections (the reconstruction uses every
            detection, weighted by its confidence).
        triangulate: ``f(pixels (T, C-1, K, 2), weights (T, C-1, K), rig) -> (T, K, 3)``
            (default :func:`~torchmocap.cameras.triangulate_dlt`).

    Returns:
        ``C`` :class:`ReprojectionScores`, one per held-out camera.
    """
    if not isinstance(detections, torch.Tensor) or detections.dim() != 4 \
            or detections.shape[-1] != 3 or detections.shape[1] != rig.num_cameras:
        shape = (tuple(detections.shape) if isinstance(detections, torch.Tensor)
                 else type(detections))
        raise ValueError(f"detections: expected shape (T, {rig.num_cameras}, K, 3), got {shape}")
    C = rig.num_cameras
    if C < 3:
        raise ValueError(f"rig: leaving one camera out needs at least 3 cameras, got {C}")
    if triangulate is None:
        from torchmocap.cameras.triangulation import triangulate_dlt as triangulate
    out = []
    for c in range(C):
        rest = [i for i in range(C) if i != c]
        sub = detections[:, rest]
        X = triangulate(sub[..., :2], sub[..., 2], rig.subset(rest))
        out.append(reprojection_scores(X, detections[:, c], rig.subset([c]), min_confidence))
    return out
