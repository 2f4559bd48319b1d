"""Scores against a view's own 2D detections: reprojection error and PCK, the
leave-one-camera-out protocol (REFERENCE §11), and a track scored in a camera it did not see
(:func:`heldout_view_scores`).

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

import math
from dataclasses import dataclass

import torch

__all__ = ["HeldOutView", "ReprojectionScores", "heldout_view_scores", "leave_one_camera_out",
           "reprojection_scores"]


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

    def summary(self) -> dict[str, float | None]:
        """The scalar scores as a plain dict (for ``metrics.json``; None where nothing was
        compared: a view without detections)."""
        def value(x: float) -> float | None:
            return None if math.isnan(x) else x

        return {"median_px": value(self.median_px), "mean_px": value(self.mean_px),
                "pck_05": value(self.pck_05), "pck_10": value(self.pck_10),
                "num_compared": self.num_compared, "num_missing": self.num_missing}


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


@dataclass
class HeldOutView:
    """A track scored in one camera's detections and masks (:func:`heldout_view_scores`).

    Attributes:
        camera: the camera's name.
        pixel_scale: the sequence's image scale; ``scores``' pixel errors are divided by it
            (pixels of the full-size images).
        scores: the track's :class:`ReprojectionScores` (``None`` without detections).
        hold_first_pose: the same of a do-nothing track that keeps the first pose.
        silhouette_iou: ``(T,)`` IoU of the capsule body with the view's masks (NaN where the
            mask is empty; None without masks).
        hold_first_iou: the same of the first pose held.
        mapping: ``{detector keypoint: {joint, frame, offset}}``: which model point each
            compared detection is compared with (joint + offset in the frame joint's bone
            frame, metres).
        min_confidence: detections above it are compared.
    """

    camera: str
    pixel_scale: float
    scores: ReprojectionScores | None
    hold_first_pose: ReprojectionScores | None
    silhouette_iou: torch.Tensor | None
    hold_first_iou: torch.Tensor | None
    mapping: dict
    min_confidence: float

    def summary(self) -> dict:
        """JSON-ready scores: ``median_px``, ``mean_px`` (full-size pixels), ``pck_05``,
        ``pck_10``, counts, ``silhouette_iou`` (mean over frames), the same of the first pose
        held (``hold_first_pose``), and the ``keypoint_mapping``."""
        out: dict = {"camera": self.camera, "pixels": "full-size images",
                     "image_scale": self.pixel_scale, "min_confidence": self.min_confidence}

        def part(scores, iou):
            d = {}
            if scores is not None:
                d.update(scores.summary())
                for k in ("median_px", "mean_px"):
                    if d[k] is not None:
                        d[k] /= self.pixel_scale
            if iou is not None:  # None: the view's masks are empty in every frame
                d["silhouette_iou"] = None if bool(iou.isnan().all()) else \
                    float(iou.nanmean())
            return d

        out.update(part(self.scores, self.silhouette_iou))
        out["hold_first_pose"] = part(self.hold_first_pose, self.hold_first_iou)
        if self.mapping:
            out["keypoint_mapping"] = self.mapping
        return out


def heldout_view_scores(seq, runtime, theta: torch.Tensor, camera: int | str = 0,
                        min_confidence: float = 0.3, silhouettes: bool = True) -> HeldOutView:
    """Score a track ``theta (T, D)`` in camera ``camera`` of ``seq`` (a view the tracker did
    not see: :func:`~torchmocap.data.split_heldout`).

    The model points compared with the view's detections are the mapped keypoints of the
    track (:func:`~torchmocap.skeleton.keypoint_positions` with ``runtime.keypoint_map``: the
    subject's fitted map, offsets scaled with the body), projected by the camera with its lens
    distortion: :func:`reprojection_scores` over every frame (the first pose was fitted without
    the view too); with masks, the IoU of the capsule body (``runtime.body``) with them. The
    do-nothing track that holds the first pose is scored alike.

    Args:
        seq: a :class:`~torchmocap.data.Sequence` holding the camera (its ``joints2d`` and
            ``silhouettes``; pixels at ``seq.meta.scale``, default 1).
        runtime: the :class:`~torchmocap.assembly.Runtime` the track was made with (skeleton,
            body, keypoint names and map).
        theta: ``(T, D)`` the track.
        camera: index or name of the camera in ``seq.rig``.
        min_confidence: detections above it are compared.
        silhouettes: also score the masks (renders the body once per frame).

    Returns:
        :class:`HeldOutView`.

    Raises:
        ValueError: an unknown camera, a track of another length, a sequence with neither
            detections nor masks.
    """
    from torchmocap.likelihoods.silhouette import render_capsule_silhouettes, silhouette_iou
    from torchmocap.skeleton import keypoint_positions, load_keypoint_map

    if seq.rig is None:
        raise ValueError("seq: expected a sequence with cameras")
    names = list(seq.rig.names)
    if isinstance(camera, str):
        if camera not in names:
            raise ValueError(f"camera: unknown camera {camera!r}; the sequence has {names}")
        camera = names.index(camera)
    if isinstance(camera, bool) or not isinstance(camera, int) or not 0 <= camera < len(names):
        raise ValueError(f"camera: expected a camera index in [0, {len(names)}) or a name, got "
                         f"{camera!r}")
    if seq.joints2d is None and seq.silhouettes is None:
        raise ValueError("seq: the view has neither 2D detections nor masks to score a track in")
    T = seq.num_frames
    if theta.dim() != 2 or theta.shape[0] != T:
        raise ValueError(f"theta: expected a track of shape ({T}, D), got {tuple(theta.shape)}")
    sk = runtime.skeleton
    rig = seq.rig.subset([camera])
    scores = first = iou = iou_first = None
    mapping: dict = {}
    if seq.joints2d is not None and runtime.keypoint_map is not None:
        kmap = load_keypoint_map(runtime.keypoint_map, sk)
        cols = kmap.columns(list(seq.joint_names), "seq.joint_names")
        det = seq.joints2d[:, camera].index_select(1, cols)

        def points(th):
            with torch.no_grad():
                kin = sk(th.to(sk.offsets.dtype))
                return keypoint_positions(kin.positions, kin.rotations, kmap).double()

        scores = reprojection_scores(points(theta), det, rig, min_confidence)
        first = reprojection_scores(points(theta[:1]).expand(T, -1, -1), det, rig,
                                    min_confidence)
        mapping = kmap.to_dict()["map"]
    if silhouettes and seq.silhouettes is not None and runtime.body is not None:
        with torch.no_grad():
            masks = seq.silhouettes[:, camera]
            H, W = masks.shape[-2:]

            def model(th):
                return render_capsule_silhouettes(runtime.body, rig,
                                                  th.to(sk.offsets.dtype))[:, :H, :W]

            # a frame whose mask is empty has no silhouette to score (NaN), not an IoU of 0
            empty = ~masks.flatten(1).any(-1)
            nan = torch.tensor(float("nan"), dtype=torch.float64)
            iou = torch.stack([nan if empty[t] else silhouette_iou(
                model(theta[t]), masks[t:t + 1])[0] for t in range(T)])
            start = model(theta[0])
            iou_first = torch.stack([nan if empty[t] else silhouette_iou(
                start, masks[t:t + 1])[0] for t in range(T)])
    scale = 1.0 if seq.meta.scale is None else seq.meta.scale
    return HeldOutView(camera=names[camera], pixel_scale=float(scale), scores=scores,
                       hold_first_pose=first, silhouette_iou=iou, hold_first_iou=iou_first,
                       mapping=mapping, min_confidence=float(min_confidence))
