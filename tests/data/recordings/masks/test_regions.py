"""Keypoint regions: glitch-robust boxes, spanning-tree distances against brute force, and the
region near a person."""

from __future__ import annotations

import numpy as np
import torch

from torchmocap.data.recordings.masks.regions import (
    _graph,
    confident_keypoints,
    keypoint_boxes,
    keypoint_graph_distance,
    person_region,
)


def _stick_figure(scale=1.0, offset=(400.0, 50.0)):
    """(K, 3) keypoints of a standing figure, 200 px tall at scale 1."""
    pts = torch.tensor([[0, 0], [0, 20], [-30, 30], [30, 30], [-45, 80], [45, 80], [-15, 100],
                        [15, 100], [-18, 150], [18, 150], [-20, 200], [20, 200]],
                       dtype=torch.float64) * scale + torch.tensor(offset, dtype=torch.float64)
    return torch.cat([pts, torch.full((pts.shape[0], 1), 0.9, dtype=torch.float64)], -1)


class TestConfidentKeypoints:
    def test_feature(self):
        kp = _stick_figure()
        assert bool(confident_keypoints(kp, 0.3).all())
        glitch = kp.clone()
        glitch[0, 0] = 0.0  # the detector wrote the nose at u = 0
        ok = confident_keypoints(glitch, 0.3)
        assert not bool(ok[0]) and bool(ok[1:].all())
        glitch[3, 2] = 0.1  # a low-confidence keypoint
        glitch[4, :2] = float("nan")
        ok = confident_keypoints(glitch, 0.3)
        assert ok.tolist() == [False, True, True, False, False] + [True] * 7


class TestKeypointBoxes:
    def test_cardinality(self):
        kp = _stick_figure().expand(3, 2, 12, 3)
        assert keypoint_boxes(kp, 0.3, 0.1).shape == (3, 2, 4)

    def test_feature(self):
        kp = _stick_figure()
        box = keypoint_boxes(kp, 0.3, 0.1)
        # extent 90 x 200: grown by 20 px on every side
        torch.testing.assert_close(box, torch.tensor([335.0, 30.0, 465.0, 270.0],
                                                     dtype=torch.float64))
        glitch = kp.clone()
        glitch[0, 0] = 0.0
        torch.testing.assert_close(keypoint_boxes(glitch, 0.3, 0.1),
                                   keypoint_boxes(kp[1:], 0.3, 0.1))
        few = kp.clone()
        few[2:, 2] = 0.0
        assert bool(torch.isnan(keypoint_boxes(few, 0.3, 0.1)).all())


def _segment_distance(q, a, b):
    """``(M,)`` exact distance of points ``q (M, D)`` to the segments ``a, b (E, D)``."""
    q = q[:, None]
    s = (((q - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1)).clamp(0, 1)
    return (q - a - s[..., None] * (b - a)).norm(dim=-1).amin(-1)


def _triangle_distance(q, a, b, c):
    """Exact distance of points ``q (M, D)`` to the triangle ``a b c`` (2D or 3D): inside its
    plane's projection the distance to the plane, else to its edges."""
    e1, e2 = b - a, c - a
    G = torch.stack([e1, e2]) @ torch.stack([e1, e2]).T
    rhs = (q - a) @ torch.stack([e1, e2]).T
    uv = torch.linalg.solve(G, rhs.T).T
    inside = (uv >= 0).all(-1) & (uv.sum(-1) <= 1)
    foot = a + uv @ torch.stack([e1, e2])
    edges = _segment_distance(q, torch.stack([a, b, a]), torch.stack([b, c, c]))
    return torch.where(inside, (q - foot).norm(dim=-1), edges)


class TestKeypointGraphDistance:
    def test_feature_brute_force(self):
        """Against the exact distance to the graph's segments and triangles (within half a
        cell's diagonal)."""
        g = torch.Generator().manual_seed(0)
        for dim, shape in ((2, (40, 60)), (3, (12, 15, 18))):
            pts = torch.rand(7, dim, generator=g, dtype=torch.float64) * \
                (torch.tensor(shape, dtype=torch.float64) - 1)
            dist = keypoint_graph_distance(pts, shape)
            edges, tri = _graph(pts.numpy())
            grid = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=torch.float64)
                                                for n in shape], indexing="ij"), -1)
            q = grid.reshape(-1, dim)
            exact = _segment_distance(q, pts[edges[:, 0]], pts[edges[:, 1]])
            for i, j, m in tri:
                exact = torch.minimum(exact, _triangle_distance(q, pts[i], pts[j], pts[m]))
            err = (dist.double().reshape(-1) - exact).abs().max()
            assert float(err) <= 0.5 * dim ** 0.5 + 1e-6

    def test_feature_graph(self):
        """The graph contains the spanning tree (connected), each point's 3 nearest neighbours,
        and exactly the triangles of mutually linked points."""
        from scipy.sparse.csgraph import connected_components

        xy = np.random.default_rng(0).random((9, 2))
        e, tri = _graph(xy)
        adj = np.zeros((9, 9), dtype=bool)
        adj[e[:, 0], e[:, 1]] = adj[e[:, 1], e[:, 0]] = True
        assert connected_components(adj)[0] == 1
        d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.diag(np.full(9, np.inf))
        for i, row in enumerate(np.argsort(d, axis=1)[:, :3]):
            assert adj[i, row].all()
        want = {(i, j, m) for i in range(9) for j in range(i + 1, 9) for m in range(j + 1, 9)
                if adj[i, j] and adj[j, m] and adj[i, m]}
        assert {tuple(t) for t in tri.tolist()} == want and len(want) > 0

    def test_feature_outside_points(self):
        """Graph parts outside the grid are dropped, not clipped onto its border."""
        pts = torch.tensor([[-50.0, 5.0], [-40.0, 5.0]])
        assert bool(torch.isinf(keypoint_graph_distance(pts, (10, 10))).all())


class TestPersonRegion:
    def test_feature(self):
        kp = _stick_figure(offset=(100.0, 50.0))
        region = person_region(kp, (300, 220), 0.05, 0.3)
        assert region.shape == (300, 220)
        for u, v in kp[:, :2].round().long().tolist():
            assert bool(region[v, u])
        # mid-thighs (hips at v = 150, knees at v = 200) and the torso's middle are covered
        assert bool(region[175, 84]) and bool(region[175, 116]) and bool(region[115, 100])
        # far from the figure nothing is (radius 0.05 x 200 px = 10 px)
        assert not bool(region[:, :40].any()) and not bool(region[265:].any())
        none = kp.clone()
        none[:, 2] = 0.0
        assert not bool(person_region(torch.stack([kp, none]), (300, 220), 0.05, 0.3)[1].any())
