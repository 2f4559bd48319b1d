"""Multi-view consistency of foreground masks, and gating by the subject's 2D detections.

:func:`hull_filter` carves, per frame, the visual hull of the masks requiring support from
``C − 1`` views (one view's miss does not remove the subject), keeps its largest component and
intersects every mask with that component's reprojection: what only some views see (a bystander
in two of four views, clutter, a plate's ghost) disappears. :func:`keypoint_gate` keeps only the
mask components that overlap the subject's keypoint box in that view.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchmocap.cameras.hull import visual_hull
from torchmocap.cameras.rig import CameraRig
from torchmocap.cameras.triangulation import triangulate_dlt
from torchmocap.data.recordings.masks.morphology import dilate
from torchmocap.data.recordings.masks.regions import keypoint_boxes, keypoint_graph_distance
from torchmocap.data.recordings.masks.settings import MaskError, MaskSettings

__all__ = ["hull_filter", "hull_regions", "keypoint_gate", "rig_focus_point"]

#: a person's keypoints lie within this distance (metres) of their median point
_BODY_REACH = 1.5


def rig_focus_point(rig: CameraRig) -> Tensor:
    """``(3,)`` world point closest (least squares) to all cameras' optical axes (float64)."""
    c = rig.camera_centers().double()
    d = rig.optical_axes().double()
    d = d / d.norm(dim=-1, keepdim=True)
    P = torch.eye(3, dtype=torch.float64, device=c.device) - d[:, :, None] * d[:, None, :]
    return torch.linalg.lstsq(P.sum(0), (P @ c[:, :, None]).sum(0)).solution[:, 0]


def hull_regions(rig: CameraRig, keypoints: Tensor | None, settings: MaskSettings
                 ) -> tuple[Tensor, Tensor | None, list[str]]:
    """Where to carve each frame's hull: world boxes ``(T, 3, 2)`` (float64), the subject's
    triangulated keypoints ``(T, K, 3)`` (NaN where not triangulated or an outlier; None
    without keypoints), and how each box was made.

    Boxes: ``settings.bounds`` when set; else the box around the frame's triangulated
    keypoints (confidence ≥ ``min_confidence`` in ≥ 2 views, points farther than 1.5 m from
    their median dropped) padded by ``hull_margin``; a frame with fewer than 3 such points takes
    the union of the other frames' boxes, or the cube of half-size ``hull_extent`` around
    :func:`rig_focus_point`.

    Args:
        rig: cameras at the keypoints' resolution.
        keypoints: ``(T, C, K, 3)`` (u, v, confidence) of the subject, or None (then one box,
            ``T = 1``).
    """
    dev = rig.K.device
    p = rig_focus_point(rig)
    e = settings.hull_extent
    cube = torch.stack([p - e, p + e], -1)
    if keypoints is None:
        if settings.bounds is not None:
            return torch.tensor(settings.bounds, dtype=torch.float64, device=dev)[None], None, \
                ["setting"]
        return cube[None], None, ["cameras"]
    kp = keypoints.to(dev, torch.float64)
    w = torch.where(kp[..., 2] >= settings.min_confidence, kp[..., 2], torch.zeros_like(kp[..., 2]))
    X = triangulate_dlt(kp[..., :2], w, rig)  # (T, K, 3) float64 (the pixels' dtype)
    T = X.shape[0]
    boxes = torch.empty(T, 3, 2, dtype=torch.float64, device=dev)
    ok = torch.zeros(T, dtype=torch.bool)
    for t in range(T):
        fin = torch.isfinite(X[t]).all(-1)
        if int(fin.sum()) >= 3:
            far = (X[t] - X[t][fin].median(0).values).norm(dim=-1) > _BODY_REACH
            X[t][far] = float("nan")
            fin = fin & ~far
        if int(fin.sum()) >= 3:
            boxes[t, :, 0] = X[t][fin].min(0).values - settings.hull_margin
            boxes[t, :, 1] = X[t][fin].max(0).values + settings.hull_margin
            ok[t] = True
    if settings.bounds is not None:
        b = torch.tensor(settings.bounds, dtype=torch.float64, device=dev)
        return b.expand(T, 3, 2).clone(), X, ["setting"] * T
    how = ["keypoints" if bool(o) else "" for o in ok]
    if bool(ok.any()):
        union = torch.stack([boxes[ok][:, :, 0].min(0).values, boxes[ok][:, :, 1].max(0).values],
                            -1)
        fill, name = union, "keypoints of other frames"
    else:
        fill, name = cube, "cameras"
    boxes[~ok] = fill
    return boxes, X, [h or name for h in how]


def _array_rig(rig: CameraRig, size: tuple[int, int]) -> CameraRig:
    """The same cameras with every image ``size = (H, W)`` (masks padded to one array size;
    padding is background, so a voxel projecting there is outside that mask)."""
    H, W = size
    return CameraRig(rig.K, rig.R, rig.t, (W, H), rig.dist, rig.names)


def hull_filter(masks: Tensor, rig: CameraRig, bounds: Tensor, settings: MaskSettings,
                skeletons: Tensor | None = None) -> tuple[Tensor, dict]:
    """Masks intersected with the reprojection of the largest component of their visual hull.

    Args:
        masks: ``(T, C, H, W)`` bool at the rig's resolution (views smaller than ``(H, W)``
            padded with background on the right/bottom).
        rig: the ``C`` cameras (working resolution).
        bounds: ``(T, 3, 2)`` world box of each frame's hull (see :func:`hull_regions`).
        settings: ``min_views`` (None: C − 1, at least 2), ``voxel_size``, ``hull_dilation``,
            ``hull_margin``.
        skeletons: ``(T, K, 3)`` the subject's triangulated keypoints (NaN where missing), or
            None; a frame with at least 3 keeps only voxels within ``hull_margin`` of their
            neighbourhood graph (a person standing next to the subject is not carved with it).

    Returns:
        ``(T, C, H, W)`` filtered masks and a JSON-safe dict: ``min_views``, per-frame hull
        ``volume_m3`` (largest component), ``empty_frames`` (frames whose hull was empty: their
        masks are returned unfiltered).
    """
    T, C, H, W = masks.shape
    need = max(2, C - 1) if settings.min_views is None else settings.min_views
    if need > C:
        raise MaskError(f"masks.min_views: expected at most the number of cameras ({C}), got "
                        f"{need}")
    arr = _array_rig(rig, (H, W)).to(masks.device)
    grow = max(1, round(settings.hull_dilation * H)) if settings.hull_dilation > 0 else 0
    out = masks.clone()
    volumes: list[float] = []
    empty: list[int] = []
    for t in range(T):
        carve = dilate(masks[t], grow)
        hull = visual_hull(arr, carve, bounds[t], settings.voxel_size, min_views=need)
        if skeletons is not None:
            pts = skeletons[t][torch.isfinite(skeletons[t]).all(-1)]
            if pts.shape[0] >= 3:
                grid = (pts.to(hull.origin) - hull.origin) / hull.voxel_size
                dist = keypoint_graph_distance(grid, tuple(hull.occupancy.shape))
                hull.occupancy &= (dist <= settings.hull_margin / hull.voxel_size).to(
                    hull.occupancy.device)
        part = hull.largest_component()
        volumes.append(round(part.volume, 4))
        if not bool(part.occupancy.any()):
            empty.append(t)
            continue
        out[t] = masks[t] & part.silhouettes(arr).to(masks.device)
    return out, {"min_views": need, "volume_m3": volumes, "empty_frames": empty}


def keypoint_gate(masks: Tensor, keypoints: Tensor, settings: MaskSettings) -> tuple[Tensor, dict]:
    """Keep the 8-connected components of ``masks (T, C, H, W)`` that overlap the subject's
    keypoint box in that view (keypoints ``(T, C, K, 3)`` at the masks' resolution); a view
    with fewer than 3 confident keypoints is left unchanged.

    Returns:
        the gated masks and ``{"components_removed": int, "views_ungated": int}``.
    """
    from scipy import ndimage

    T, C, H, W = masks.shape
    box = keypoint_boxes(keypoints.to(torch.float64), settings.min_confidence,
                         settings.keypoint_margin).reshape(T * C, 4).cpu()
    gated = torch.isfinite(box).all(-1)
    s = np.zeros((3, 3, 3), dtype=bool)
    s[1] = True
    labels, n = ndimage.label(masks.reshape(T * C, H, W).cpu().numpy(), structure=s)
    keep = np.zeros(n + 1, dtype=bool)
    for i in range(T * C):
        if bool(gated[i]):
            u0, v0 = (max(0, math.ceil(float(x))) for x in box[i, :2])
            u1, v1 = (math.floor(float(x)) for x in box[i, 2:])
            region = labels[i, v0:v1 + 1, u0:u1 + 1] if u1 >= u0 and v1 >= v0 else labels[i, :0]
        else:
            region = labels[i]
        keep[np.unique(region)] = True
    keep[0] = False
    removed = int(n - keep.sum())
    out = torch.from_numpy(keep[labels]).to(masks.device).reshape(T, C, H, W)
    return out, {"components_removed": removed, "views_ungated": int((~gated).sum())}
