"""Image regions from 2D keypoints: robust boxes, and the area near a detected person.

The keypoints' format (BODY_25, COCO, …) is not assumed: a person's limbs are approximated by
the minimum spanning tree of the confident keypoints (bones link nearby joints), drawn as
capsules.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["confident_keypoints", "keypoint_boxes", "person_region", "spanning_tree_distance"]


def confident_keypoints(keypoints: Tensor, min_confidence: float) -> Tensor:
    """``(*, K)`` bool: confidence ≥ ``min_confidence``, finite pixels, and not isolated — a
    keypoint whose nearest confident neighbour is farther than the median distance between
    confident keypoints is a detector glitch (e.g. a nose written at u = 0)."""
    kp = keypoints.to(torch.float64)
    ok = (kp[..., 2] >= min_confidence) & torch.isfinite(kp[..., :2]).all(-1)
    xy = torch.where(ok[..., None], kp[..., :2], torch.zeros_like(kp[..., :2]))
    d = (xy[..., :, None, :] - xy[..., None, :, :]).norm(dim=-1)  # (*, K, K)
    pair = ok[..., :, None] & ok[..., None, :]
    K = kp.shape[-2]
    pair = pair & ~torch.eye(K, dtype=torch.bool, device=kp.device)
    nearest = torch.where(pair, d, torch.full_like(d, float("inf"))).amin(-1)
    med = torch.where(pair, d, torch.full_like(d, float("nan"))).flatten(-2).nanmedian(-1).values
    isolated = nearest > med[..., None]
    return ok & ~(isolated & (ok.sum(-1, keepdim=True) >= 4))


def keypoint_boxes(keypoints: Tensor, min_confidence: float, margin: float) -> Tensor:
    """Boxes ``(*, 4)`` (u0, v0, u1, v1) around the :func:`confident_keypoints` of
    ``(*, K, 3)`` (u, v, confidence), grown by ``margin`` × the box's larger side on every side;
    NaN where fewer than 3 keypoints qualify.

    Example:
        >>> kp = torch.tensor([[10.0, 20.0, 1.0], [30.0, 60.0, 1.0], [20.0, 40.0, 1.0]])
        >>> keypoint_boxes(kp, 0.5, 0.1).tolist()
        [6.0, 16.0, 34.0, 64.0]
    """
    ok = confident_keypoints(keypoints, min_confidence)
    kp = keypoints.to(torch.float64)
    inf = torch.full_like(kp[..., 0], float("inf"))
    u, v = kp[..., 0], kp[..., 1]
    u0 = torch.where(ok, u, inf).amin(-1)
    v0 = torch.where(ok, v, inf).amin(-1)
    u1 = torch.where(ok, u, -inf).amax(-1)
    v1 = torch.where(ok, v, -inf).amax(-1)
    grow = margin * torch.maximum(u1 - u0, v1 - v0)
    box = torch.stack([u0 - grow, v0 - grow, u1 + grow, v1 + grow], -1)
    enough = ok.sum(-1) >= 3
    return torch.where(enough[..., None], box, torch.full_like(box, float("nan")))


def _spanning_edges(points: np.ndarray) -> np.ndarray:
    """``(E, 2)`` index pairs of the minimum spanning tree of points ``(N, D)``."""
    from scipy.sparse.csgraph import minimum_spanning_tree
    from scipy.spatial.distance import cdist

    if points.shape[0] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    # coincident points get a tiny distance: a zero weight would mean "no edge"
    tree = minimum_spanning_tree(cdist(points, points) + 1e-9).tocoo()
    return np.stack([tree.row, tree.col], 1).astype(np.int64)


def spanning_tree_distance(points: Tensor, shape: tuple[int, ...]) -> Tensor:
    """Distance (grid units) from every cell of a grid to the minimum spanning tree of
    ``points (N, D)`` (N ≥ 1), given in grid index coordinates (cell ``i`` is centred at
    ``i``): ``(*shape)`` float32.

    The tree's edges are sampled every half cell into the grid (samples outside it are
    dropped) and the Euclidean distance transform measures the rest, so the result is exact to
    half a cell.

    Example:
        >>> pts = torch.tensor([[0.0, 0.0], [0.0, 8.0]])
        >>> spanning_tree_distance(pts, (3, 9))[2].tolist()
        [2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0]
    """
    from scipy import ndimage

    p = points.detach().to(torch.float64).cpu()
    e = torch.from_numpy(_spanning_edges(p.numpy()))
    samples = [p]
    if e.shape[0]:
        a, b = p[e[:, 0]], p[e[:, 1]]
        n = int(((b - a).norm(dim=-1).max() * 2).ceil()) + 1
        s = torch.linspace(0, 1, n, dtype=torch.float64)
        samples.append((a[:, None] + s[None, :, None] * (b - a)[:, None]).reshape(-1, p.shape[1]))
    idx = torch.cat(samples).round().long()
    size = torch.tensor(shape)
    idx = idx[((idx >= 0) & (idx < size)).all(-1)]
    seeds = np.ones(shape, dtype=bool)
    seeds[tuple(idx.T.numpy())] = False
    if seeds.all():
        return torch.full(shape, float("inf"), device=points.device)
    return torch.from_numpy(ndimage.distance_transform_edt(seeds).astype(np.float32)
                            ).to(points.device)


def person_region(keypoints: Tensor, size: tuple[int, int], radius: float,
                  min_confidence: float) -> Tensor:
    """Pixels near a detected person: ``(*, H, W)`` bool.

    Each image's :func:`confident_keypoints` (at least 3) are linked by their minimum spanning
    tree; a pixel is in the region when it lies within ``radius`` × the keypoints' larger
    extent (box width or height) of a keypoint or of a tree edge. Images with fewer than 3
    confident keypoints give an empty region.

    Args:
        keypoints: ``(*, K, 3)`` (u, v, confidence) in pixels.
        size: ``(H, W)`` of the region images.
        radius: capsule radius as a fraction of the person's extent.
        min_confidence: keypoints below it are ignored.
    """
    H, W = size
    lead = keypoints.shape[:-2]
    kp = keypoints.reshape(-1, *keypoints.shape[-2:]).to(torch.float64)
    ok = confident_keypoints(kp, min_confidence)
    out = torch.zeros(kp.shape[0], H, W, dtype=torch.bool, device=keypoints.device)
    for i in range(kp.shape[0]):
        pts = kp[i, ok[i], :2]
        if pts.shape[0] < 3:
            continue
        r = radius * float((pts.max(0).values - pts.min(0).values).max())
        u0, v0 = (pts.min(0).values - r).floor().long().tolist()
        u1, v1 = (pts.max(0).values + r).ceil().long().tolist()
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, W - 1), min(v1, H - 1)
        if u1 < u0 or v1 < v0:
            continue
        # grid (row, column) = (v − v0, u − u0)
        local = torch.stack([pts[:, 1] - v0, pts[:, 0] - u0], -1)
        dist = spanning_tree_distance(local, (v1 - v0 + 1, u1 - u0 + 1))
        out[i, v0:v1 + 1, u0:u1 + 1] = dist <= r
    return out.reshape(*lead, H, W)
