"""Lines of sight blocked by capsules (self-occlusion of the appearance term)."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body import rays_blocked_by_capsules, segment_distance


def _oracle(origins, points, endpoints, radii, own, stop, samples=4001):
    """Dense sampling of each line of sight: the smallest distance of a sample to every
    capsule axis (``segment_distance``), compared with the radius. Also returns the margin
    ``min_b |d_b - r_b|`` so that grazing cases can be left out."""
    C, (P, N) = origins.shape[0], points.shape[:2]
    s = torch.linspace(0, 1, samples, dtype=points.dtype)
    blocked = torch.zeros(C, P, N, dtype=torch.bool)
    margin = torch.full((C, P, N), float("inf"), dtype=points.dtype)
    for c in range(C):
        d = points - origins[c]
        end = origins[c] + d * (1 - stop / d.norm(dim=-1, keepdim=True))  # (P, N, 3)
        ray = origins[c] + s[None, None, :, None] * (end - origins[c])[:, :, None]  # (P,N,S,3)
        for p in range(P):
            dist = segment_distance(ray[p].reshape(-1, 3), endpoints[p]).reshape(
                N, samples, -1).amin(1)  # (N, B)
            dist = torch.where(torch.arange(endpoints.shape[1])[None] == own[:, None],
                               torch.inf, dist)
            blocked[c, p] = (dist < radii).any(-1)
            margin[c, p] = (dist - radii).abs().amin(-1)
    return blocked, margin


def test_matches_a_dense_sampling_oracle():
    g = torch.Generator().manual_seed(0)
    P, B, N = 3, 5, 40
    endpoints = torch.rand(P, B, 2, 3, generator=g, dtype=torch.float64) * 2 - 1
    radii = 0.05 + 0.2 * torch.rand(B, generator=g, dtype=torch.float64)
    points = torch.rand(P, N, 3, generator=g, dtype=torch.float64) * 2 - 1
    own = torch.randint(0, B, (N,), generator=g)
    origins = torch.tensor([[0.0, 0.0, 4.0], [3.0, 1.0, 0.0], [-2.5, -2.5, 0.5]],
                           dtype=torch.float64)
    got = rays_blocked_by_capsules(origins, points, endpoints, radii, own, stop=0.01)
    want, margin = _oracle(origins, points, endpoints, radii, own, 0.01)
    clear = margin > 2e-3  # the oracle's sampling step is ~1.5 mm
    assert clear.float().mean() > 0.9
    assert torch.equal(got[clear], want[clear])
    assert 0.1 < want[clear].float().mean() < 0.9  # both outcomes are exercised


def test_simple_cases():
    o = torch.tensor([[0.0, 0.0, 5.0]])
    # a capsule along x at z = 2 between the camera and the origin; the point's own is index 1
    endpoints = torch.tensor([[[[-1.0, 0.0, 2.0], [1.0, 0.0, 2.0]],
                               [[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]]]])
    radii = torch.tensor([0.1, 0.4])
    pts = torch.tensor([[[0.0, 0.0, 0.3],      # behind capsule 0: hidden
                         [0.0, 0.5, 0.3],      # beside it in y: seen
                         [0.0, 0.0, 2.5]]])    # in front of it: seen
    own = torch.tensor([1, 1, 1])
    got = rays_blocked_by_capsules(o, pts, endpoints, radii, own)
    assert got.tolist() == [[[True, False, False]]]
    # the point's own capsule (radius 0.4 around the y axis) never hides it; without the
    # exclusion the first two points lie inside it and are hidden
    no_own = rays_blocked_by_capsules(o, pts, endpoints, radii, None)
    assert no_own.tolist() == [[[True, True, False]]]
    with pytest.raises(ValueError, match="origins"):
        rays_blocked_by_capsules(o[0], pts, endpoints, radii)
    with pytest.raises(ValueError, match="points"):
        rays_blocked_by_capsules(o, pts[0], endpoints, radii)
    with pytest.raises(ValueError, match="endpoints"):
        rays_blocked_by_capsules(o, pts, endpoints[0], radii)
    with pytest.raises(ValueError, match="radii"):
        rays_blocked_by_capsules(o, pts, endpoints, radii[:1])
    with pytest.raises(ValueError, match="own"):
        rays_blocked_by_capsules(o, pts, endpoints, radii, own[:2])
