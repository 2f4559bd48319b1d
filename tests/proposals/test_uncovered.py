"""Data-driven limb jumps into unexplained foreground (UncoveredLimbProposal): on masks rendered
with a *different* (thicker) body whose left arm is raised, regrown arms of the standing model
land on the raised arm; the pure pieces by closed forms; bad input as typed errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import render_capsule_silhouettes
from torchmocap.proposals import (
    GaussianDiffusionProposal,
    ProposalContext,
    UncoveredLimbProposal,
    draw_limb_targets,
    foreground_points,
    unexplained_distance,
)
from torchmocap.skeleton import human31


@pytest.fixture(scope="module")
def scene():
    sk = human31()
    rig = make_ring_rig(4).float()
    truth = sk.zero_pose()
    truth[sk.dof_index("l_shoulder_abd")] = math.radians(90)  # left arm held out sideways
    truth[sk.dof_index("l_elbow_flex")] = math.radians(20)
    other = CapsuleBody(sk).float()  # the subject: a different, 20 % thicker body
    other.radii.mul_(1.2)
    masks = render_capsule_silhouettes(other, rig, truth)
    frame = Frame(index=0, time=0.0, silhouettes=masks)
    return sk, CapsuleBody(sk).float(), rig, truth, frame


def _still(sk):
    """A base proposal that returns its ancestors (the jumps alone are tested)."""
    return GaussianDiffusionProposal(0.0, num_dofs=sk.num_dofs)


def test_regrown_arm_lands_on_the_raised_arm(scene):
    sk, body, rig, truth, frame = scene
    start = sk.zero_pose()  # the generic standing start: arms down
    prop = UncoveredLimbProposal(_still(sk), sk, body, rig, chains=["l_arm", "r_arm"],
                                 jump_prob=1.0, voxel=0.04)
    out = prop.sample(ProposalContext(start, frame=frame), 120,
                      torch.Generator().manual_seed(0))
    x = out.particles
    assert out.stats["jumped"] > 60 and out.stats["hull_points"] > 100
    assert bool(sk.within_limits(x, tol=1e-5).all())
    pos, want = sk(x).positions, sk(truth).positions
    moved_l = (x[:, sk.dof_index("l_shoulder_abd")] != 0)
    wl, wr = sk.joint_index("l_wrist"), sk.joint_index("r_wrist")
    err_l = (pos[moved_l, wl] - want[wl]).norm(dim=-1)
    err_start = float((sk(start).positions[wl] - want[wl]).norm())
    assert err_start > 0.5
    # most regrown left arms reach the raised arm (the wrist within a forearm's width)
    assert float((err_l < 0.12).float().mean()) > 0.6, err_l
    # a regrown right arm stays where the truth's is (its own foreground, not the left arm's)
    moved_r = (x[:, sk.joint_dofs("r_shoulder")] != 0).any(1)
    err_r = (pos[moved_r, wr] - want[wr]).norm(dim=-1)
    assert float(err_r.median()) < 0.12, err_r
    # the other DoFs are the base's draws
    lim = [d for d in range(sk.num_dofs) if d not in sk.joint_dofs("l_shoulder")
           + sk.joint_dofs("l_elbow") + sk.joint_dofs("r_shoulder") + sk.joint_dofs("r_elbow")]
    assert torch.equal(x[:, lim], start[lim].expand(120, -1))


def test_no_jump_without_usable_foreground(scene):
    sk, body, rig, truth, frame = scene
    prop = UncoveredLimbProposal(_still(sk), sk, body, rig, jump_prob=1.0, voxel=0.05)
    empty = Frame(index=1, time=0.0, silhouettes=torch.zeros_like(frame.silhouettes))
    out = prop.sample(ProposalContext(truth, frame=empty), 10, torch.Generator().manual_seed(1))
    assert out.stats["fallback_hull"] == 1 and out.stats["jumped"] == 0
    assert torch.equal(out.particles, truth.expand(10, -1))
    # every view dropped: no hull either
    dropped = Frame(index=2, time=0.0, silhouettes=frame.silhouettes,
                    view_dropped=torch.ones(4, dtype=torch.bool))
    out = prop.sample(ProposalContext(truth, frame=dropped), 4, torch.Generator())
    assert out.stats["fallback_hull"] == 1
    with pytest.raises(ValueError, match="context.frame"):
        prop.sample(ProposalContext(truth), 4, torch.Generator())


def test_foreground_points_are_the_visual_hull(scene):
    sk, body, rig, truth, frame = scene
    bounds = torch.tensor([[-1.5, 1.5], [-1.5, 1.5], [-0.1, 2.0]])
    pts = foreground_points(rig, frame.silhouettes, bounds, 0.05)
    # every hull voxel projects into every mask, and the truth's joints are surrounded by them
    pix, _, vis = rig.project(pts)
    u, v = pix[..., 0].round().long(), pix[..., 1].round().long()
    c = torch.arange(4)[:, None].expand_as(u)
    assert bool(vis.all()) and bool(frame.silhouettes[c, v, u].all())
    d = torch.cdist(sk(truth).positions.to(pts), pts).amin(1)
    assert float(d.max()) < 0.06
    with pytest.raises(ValueError, match="masks"):
        foreground_points(rig, frame.silhouettes[:2], bounds, 0.05)
    with pytest.raises(ValueError, match="voxel"):
        foreground_points(rig, frame.silhouettes, bounds, 0.0)


def test_unexplained_distance_closed_form():
    ends = torch.tensor([[[[0.0, 0, 0], [0, 0, 1]], [[5.0, 0, 0], [5, 0, 1]]]])  # (1, 2, 2, 3)
    r = torch.tensor([0.1, 0.2])
    pts = torch.tensor([[1.0, 0, 0.5], [0.0, 0, 0.5], [4.0, 0, 2.0]])
    d = unexplained_distance(pts, ends, r)
    want = torch.tensor([[0.9, -0.1, math.sqrt(2.0) - 0.2]])
    assert torch.allclose(d, want, atol=1e-6)
    d = unexplained_distance(pts, ends, r, keep=torch.tensor([False, True]))
    assert torch.allclose(d[0, 0], torch.tensor(4.0 - 0.2), atol=1e-6)
    assert bool(torch.isinf(unexplained_distance(pts, ends, r, torch.tensor([False, False])))
                .all())
    with pytest.raises(ValueError, match="endpoints"):
        unexplained_distance(pts, ends[0], r)


def test_draw_limb_targets_geometry():
    g = torch.Generator().manual_seed(3)
    # candidate points: a straight horizontal "arm" of points from the root along +x
    pts = torch.stack([torch.linspace(0.05, 0.8, 31), torch.zeros(31), torch.zeros(31)], -1)
    P = 50
    root = torch.zeros(P, 3)
    cur = torch.tensor([[0.0, 0, -0.3], [0, 0, -0.55]]).expand(P, 2, 3)
    lengths, radii = torch.tensor([0.3, 0.25]), torch.tensor([0.05, 0.04])
    w = (pts[:, 0] > 0.4).float().expand(P, -1)  # only the far points pull
    tg, found = draw_limb_targets(pts, w, root, cur, lengths, radii, 0.03, 0.02, g)
    assert bool(found.all())
    # the end on the arm's line within reach, the hinge on its circle (a point of the line)
    assert torch.allclose(tg[:, 1, 1:], torch.zeros(P, 2), atol=1e-6)
    assert bool(((tg[:, 1, 0] > 0.4) & (tg[:, 1, 0] <= 0.55 + 1e-6)).all())
    assert bool(((tg[:, 0].norm(dim=-1) - 0.3).abs() <= 0.03 + 1e-6).all())
    # no candidate in reach: the current joints are kept and the row is flagged
    far = torch.zeros(P, 31)
    tg, found = draw_limb_targets(pts, far, root, cur, lengths, radii, 0.03, 0.02, g)
    assert not bool(found.any()) and torch.equal(tg, cur)
    with pytest.raises(ValueError, match="weight"):
        draw_limb_targets(pts, -w, root, cur, lengths, radii, 0.03, 0.02, g)
    with pytest.raises(ValueError, match="root, current"):
        draw_limb_targets(pts, w, root[:3], cur, lengths, radii, 0.03, 0.02, g)


def test_constructor_errors(scene):
    sk, body, rig, truth, frame = scene
    base = _still(sk)
    with pytest.raises(TypeError, match="base"):
        UncoveredLimbProposal("gaussian", sk, body, rig)
    with pytest.raises(ValueError, match="jump_prob"):
        UncoveredLimbProposal(base, sk, body, rig, jump_prob=1.5)
    with pytest.raises(ValueError, match="voxel"):
        UncoveredLimbProposal(base, sk, body, rig, voxel=0)
    with pytest.raises(ValueError, match="tries"):
        UncoveredLimbProposal(base, sk, body, rig, tries=0)
    with pytest.raises(ValueError, match="chains"):
        UncoveredLimbProposal(base, sk, body, rig, chains=["l_tail"])
    with pytest.raises(ValueError, match="rig, body"):
        UncoveredLimbProposal(base, sk, body, None)
    prop = UncoveredLimbProposal(base, sk, body, rig)
    assert prop.requires == ("silhouettes",) and prop.coordinate_std is base.coordinate_std
