"""Image regions from 2D keypoints: robust boxes, and the area near a detected person.

The keypoints' format (BODY_25, COCO, …) is not assumed: a person's limbs are approximated by
the neighbourhood graph of the confident keypoints (minimum spanning tree plus nearest
neighbours: bones link nearby joints; its triangles span the torso), thickened by a radius.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torchmocap.data.recordings.masks.morphology import fill_holes

__all__ = ["confident_keypoints", "keypoint_boxes", "keypoint_graph_distance", "person_region"]


def confident_keypoints(keypoints: Tensor, min_confidence: float) -> Tensor:
    """``(*, K)`` bool: confidence ≥ ``min_confidence``, finite pixels, and not isolated.

    A keypoint is isolated — a detector glitch such as a nose written at u = 0 — when its
    nearest confident neighbour is farther than both 3 × the median nearest-neighbour distance
    and half the median distance between confident keypoints (a stretched forearm is neither).
    Only sets of at least 4 keypoints are checked.
    """
    kp = keypoints.to(torch.float64)
    ok = (kp[..., 2] >= min_confidence) & torch.isfinite(kp[..., :2]).all(-1)
    xy = torch.where(ok[..., None], kp[..., :2], torch.zeros_like(kp[..., :2]))
    d = (xy[..., :, None, :] - xy[..., None, :, :]).norm(dim=-1)  # (*, K, K)
    K = kp.shape[-2]
    pair = ok[..., :, None] & ok[..., None, :] & ~torch.eye(K, dtype=torch.bool,
                                                           device=kp.device)
    nan = torch.full_like(d, float("nan"))
    nearest = torch.where(pair, d, torch.full_like(d, float("inf"))).amin(-1)  # (*, K)
    typical = torch.where(ok, nearest, torch.full_like(nearest, float("nan"))).nanmedian(-1)
    spread = torch.where(pair, d, nan).flatten(-2).nanmedian(-1).values
    limit = torch.maximum(3 * typical.values, 0.5 * spread)
    isolated = nearest > limit[..., None]
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


def _graph(points: np.ndarray, k: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Neighbourhood graph of ``points (N, D)``: ``(E, 2)`` edges — the minimum spanning tree
    (it connects everything) and each point's ``k`` nearest neighbours (so both thighs of a
    standing person are drawn, not only the link between the knees) — and ``(F, 3)`` its
    triangles (three mutually linked points: the torso between shoulders and hips)."""
    from scipy.sparse.csgraph import minimum_spanning_tree
    from scipy.spatial.distance import cdist

    n = points.shape[0]
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 3), dtype=np.int64)
    d = cdist(points, points)
    # coincident points get a tiny distance: a zero weight would mean "no edge"
    tree = minimum_spanning_tree(d + 1e-9).tocoo()
    np.fill_diagonal(d, np.inf)
    near = np.argsort(d, axis=1)[:, :min(k, n - 1)]
    knn = np.stack([np.repeat(np.arange(n), near.shape[1]), near.ravel()], 1)
    edges = np.concatenate([np.stack([tree.row, tree.col], 1), knn]).astype(np.int64)
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    adj = np.zeros((n, n), dtype=bool)
    adj[edges[:, 0], edges[:, 1]] = adj[edges[:, 1], edges[:, 0]] = True
    tri = [(i, j, m) for i, j in edges for m in np.flatnonzero(adj[i] & adj[j]) if m > j]
    return edges, np.array(tri, dtype=np.int64).reshape(-1, 3)


def _graph_samples(p: Tensor, edges: Tensor, triangles: Tensor) -> Tensor:
    """Points every half cell on the graph's edges and triangles, ``(M, D)``."""
    out = [p]
    if edges.shape[0]:
        a, b = p[edges[:, 0]], p[edges[:, 1]]
        n = int(((b - a).norm(dim=-1).max() * 2).ceil()) + 1
        s = torch.linspace(0, 1, n, dtype=p.dtype)
        out.append((a[:, None] + s[None, :, None] * (b - a)[:, None]).reshape(-1, p.shape[1]))
    for i, j, m in triangles.tolist():
        a, b, c = p[i], p[j], p[m]
        n = int((torch.stack([b - a, c - a, c - b]).norm(dim=-1).max() * 2).ceil()) + 1
        s = torch.linspace(0, 1, n, dtype=p.dtype)
        u, v = torch.meshgrid(s, s, indexing="ij")
        keep = (u + v) <= 1
        out.append(a + u[keep, None] * (b - a) + v[keep, None] * (c - a))
    return torch.cat(out)


def keypoint_graph_distance(points: Tensor, shape: tuple[int, ...]) -> Tensor:
    """Distance (grid units) from every cell of a grid to the neighbourhood graph of
    ``points (N, D)`` (N ≥ 1; minimum spanning tree plus 3 nearest neighbours each, and the
    triangles they form — limbs and torso, for a person's keypoints), given in grid index
    coordinates (cell ``i`` is centred at ``i``): ``(*shape)`` float32.

    The graph's edges and triangles are sampled every half cell into the grid (samples outside
    it are dropped) and the Euclidean distance transform measures the rest, so the result is
    exact to half a cell (diagonal).

    Example:
        >>> pts = torch.tensor([[0.0, 0.0], [0.0, 8.0]])
        >>> keypoint_graph_distance(pts, (3, 9))[2].tolist()
        [2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0]
    """
    from scipy import ndimage

    p = points.detach().to(torch.float64).cpu()
    edges, triangles = (torch.from_numpy(a) for a in _graph(p.numpy()))
    idx = _graph_samples(p, edges, triangles).round().long()
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

    Each image's :func:`confident_keypoints` (at least 3) are linked by their neighbourhood
    graph (:func:`keypoint_graph_distance`); a pixel is in the region when it lies within
    ``radius`` × the keypoints' larger extent (box width or height) of a keypoint, an edge or
    a triangle of that graph, or is enclosed by such capsules (the torso inside a loop of
    limbs). Images with fewer than 3
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
        dist = keypoint_graph_distance(local, (v1 - v0 + 1, u1 - u0 + 1))
        out[i, v0:v1 + 1, u0:u1 + 1] = dist <= r
    # limbs that form a loop (shoulders, arms, hips) enclose the torso: fill it
    return fill_holes(out).reshape(*lead, H, W)
