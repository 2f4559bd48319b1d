"""Scores of a track in the camera views: the 2D error of the projected joints against the
detections (and the truth's projections), and the silhouette IoU of the model against the
masks (the score of a recording without ground truth)."""

from __future__ import annotations

import torch

__all__ = ["reprojection_error", "silhouette_agreement"]


def reprojection_error(seq, skeleton, rig, theta: torch.Tensor,
                       min_confidence: float = 0.5) -> dict:
    """2D error (pixels) of the estimate's projected joints against the sequence's 2D joint
    detections of confidence >= ``min_confidence`` (``vs_detections``) and, with ground truth,
    against the true joints' projections (``vs_truth``), over frames 1..T-1 and every camera.
    ``{}`` when the detections are not the skeleton's joints (another keypoint set)."""
    pos = skeleton(theta[1:]).positions  # (T-1, J, 3)
    pix, _, vis = rig.project(pos.to(rig.K.dtype))  # (T-1, C, J, 2)
    det = seq.joints2d[1:].to(pix.dtype)
    if det.shape[-2] != pix.shape[-2]:
        return {}
    ok = (det[..., 2] >= min_confidence) & vis
    out = {}
    if bool(ok.any()):
        out["vs_detections"] = float((pix - det[..., :2]).norm(dim=-1)[ok].mean())
    if seq.ground_truth is not None:
        tp, _, tvis = rig.project(seq.ground_truth.positions[1:].to(pix.dtype))
        m = vis & tvis
        if bool(m.any()):
            out["vs_truth"] = float((pix - tp).norm(dim=-1)[m].mean())
    return out


def silhouette_agreement(seq, body, rig, theta: torch.Tensor) -> dict:
    """Per-view silhouette IoU of the model capsules at ``theta (T, D)`` against the masks:
    ``{per_view (of the last frame), mean (of the last frame), mean_over_frames}``; ``{}``
    without masks or cameras. A view whose mask is empty has nothing to score: None in
    ``per_view``, left out of the means (None when no view has a mask)."""
    from torchmocap.likelihoods import render_capsule_silhouettes, silhouette_iou

    if seq.silhouettes is None or rig is None:
        return {}

    def mean(values):
        seen = [v for v in values if v is not None]
        return sum(seen) / len(seen) if seen else None

    per = []
    for t in range(seq.num_frames):
        model = render_capsule_silhouettes(body, rig, theta[t])
        has = seq.silhouettes[t].flatten(1).any(-1).tolist()
        per.append([float(v) if h else None
                    for v, h in zip(silhouette_iou(model, seq.silhouettes[t]), has)])
    last = per[-1]
    frames = [m for m in (mean(p) for p in per) if m is not None]
    return {"per_view": last, "mean": mean(last),
            "mean_over_frames": sum(frames) / len(frames) if frames else None}
