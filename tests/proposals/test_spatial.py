"""Hauberg & Pedersen's proposals: the projected spatial prior, the silhouette- and depth-driven
importance distributions, the whole-pose rejection sampler; and the point-cloud likelihood."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import PointCloudLikelihood, Poses
from torchmocap.proposals import (
    AngularPriorProposal,
    InSilhouette,
    JointCriterion,
    NearPointCloud,
    PoseInSilhouette,
    PreviousFrame,
    ProposalContext,
    RejectionProposal,
    SpatialPriorProposal,
    tracked_joints,
)
from torchmocap.proposals.angular import free_dofs
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parents[1] / "likelihoods"))
from oracle import capsule_masks  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    sk = human31()
    body = CapsuleBody(sk).float()
    rig = make_ring_rig(1).float()
    th = sk.zero_pose()
    th[sk.dof_index("l_shoulder_abd")] = 0.9
    th[sk.dof_index("r_elbow_flex")] = 1.0
    masks = capsule_masks(body, rig, th)
    # a point cloud on the camera-facing skin of the pose
    kin = sk(th[None])
    pts, normals, _ = body.sample_surface_points(kin, 3000, torch.Generator().manual_seed(0))
    c = rig.camera_centers()[0]
    facing = ((c - pts[0]) * normals[0]).sum(-1) > 0
    return sk, body, rig, th, masks, pts[0][facing]


def test_tracked_joints():
    sk = human31()
    names = [sk.joint_names[j] for j in tracked_joints(sk, free_dofs(sk, ["l_elbow"]))]
    assert names == ["l_wrist", "l_hand"]
    upper = [sk.joint_names[j] for j in tracked_joints(sk, free_dofs(sk, "upper_body"))]
    assert "l_knee" not in upper and "l_hand" in upper and "head_top" in upper
    assert len(tracked_joints(sk, free_dofs(sk, "all"))) == 21


def test_spatial_prior_moves_only_the_tracked_dofs_and_stays_in_limits(scene):
    sk, body, rig, th, masks, _ = scene
    prop = SpatialPriorProposal(sk, position_std=0.04, joints="upper_body")
    out = prop.sample(ProposalContext(th), 300, torch.Generator().manual_seed(0))
    x = out.particles
    assert bool(sk.within_limits(x, tol=1e-5).all())
    frozen = [d for d in range(31) if d not in prop.free.tolist()]
    assert torch.equal(x[:, frozen], th[frozen].expand(300, -1))
    # the hands scatter by about the position std (not the growing angular spread)
    hand = sk.joint_index("l_hand")
    spread = (sk(x).positions[:, hand] - sk(th).positions[hand]).norm(dim=-1).median()
    assert 0.02 < float(spread) < 0.12
    assert out.log_q is None  # a projected density has no closed form


def test_silhouette_driven_joints_land_in_the_foreground(scene):
    sk, body, rig, th, masks, _ = scene
    frame = Frame(index=0, time=0.0, silhouettes=masks)
    crit = InSilhouette(rig)
    st = crit.prepare(frame)
    g = torch.Generator().manual_seed(1)
    blind = SpatialPriorProposal(sk, position_std=0.06, joints="upper_body")
    driven = SpatialPriorProposal(sk, position_std=0.06, joints="upper_body", criteria=[crit])
    fractions = []
    for prop in (blind, driven):
        out = prop.sample(ProposalContext(th, frame=frame), 300, g)
        pos = sk(out.particles).positions[:, prop.joint_index]
        ok = crit(pos.reshape(-1, 3), prop.joint_index.repeat(300), st)
        fractions.append(float(ok.float().mean()))
    assert fractions[1] > fractions[0] + 0.1, fractions
    assert out.stats["failed_joints"] == 0 and out.stats["joint_tries"] > 1
    # no foreground at all: the criterion is switched off and the frame says so
    empty = Frame(index=1, time=0.0, silhouettes=torch.zeros_like(masks))
    out = driven.sample(ProposalContext(th, frame=empty), 50, g)
    assert out.stats.get("fallback_silhouette") == 1
    with pytest.raises(ValueError, match="context.frame"):
        driven.sample(ProposalContext(th), 5, g)


class _BeyondPlane(JointCriterion):
    """Accepts points whose first coordinate exceeds ``a`` (a closed-form acceptance rate)."""

    name = "plane"

    def __init__(self, a):
        self.a, self.calls, self.seen = a, 0, 0

    def __call__(self, points, joints, state):
        self.calls += 1
        self.seen += points.shape[0]
        return points[:, 0] > self.a


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_per_joint_rejection_matches_one_at_a_time_sampling(seed):
    """The batched rounds draw what sequential rejection draws: accepted joints follow the
    normal truncated to the criterion, tries are geometric capped at ``max_tries``, a joint
    that never passes keeps a draw from the untruncated normal; in O(log max_tries) rounds."""
    sk = human31()
    a, cap, P = 1.0, 8, 1500
    prop = SpatialPriorProposal(sk, criteria=[_BeyondPlane(a)], max_tries=cap)
    crit = prop.criteria[0]
    L = prop.joint_index.numel()
    g = torch.Generator().manual_seed(seed)
    mu = torch.zeros(P, L, 3, dtype=torch.float64)
    std = torch.ones(P, L, 1, dtype=torch.float64)
    x0 = torch.randn(P, L, 3, generator=g, dtype=torch.float64)
    x, tries, failed = prop._reject(x0.clone(), mu, std, [(crit, None)], g)
    p = 1 - 0.5 * math.erfc(-a / math.sqrt(2))  # P(N(0, 1) > a)
    n = P * L
    ok = x[..., 0] > a
    # failures: (1 - p)^cap of the joints, and exactly those that are not beyond the plane
    assert failed == int((~ok).sum())
    q = (1 - p) ** cap
    assert abs(failed / n - q) < 4 * math.sqrt(q * (1 - q) / n)
    assert bool((tries[~ok] == cap).all()) and int(tries.max()) == cap
    # mean tries of a capped geometric: (1 - (1 - p)^cap) / p
    m_t = (1 - q) / p
    assert abs(float(tries.double().mean()) - m_t) < 0.03 * m_t
    # accepted draws: the normal truncated at a (mean phi(a) / p); the other coordinates
    # untouched by the criterion stay standard normal
    phi = math.exp(-a * a / 2) / math.sqrt(2 * math.pi)
    assert abs(float(x[..., 0][ok].mean()) - phi / p) < 0.02
    assert abs(float(x[..., 1][ok].std()) - 1.0) < 0.03
    # joints accepted at the first draw keep it
    first = x0[..., 0] > a
    assert torch.equal(x[first], x0[first]) and bool((tries[first] == 1).all())
    # rounds: the initial check plus batches 1, 2, 4, (1): at most 5 calls for cap 8
    assert crit.calls <= 5


class _InBall(JointCriterion):
    """Accepts points within ``r`` of the origin; records how many points it was asked about."""

    name = "ball"

    def __init__(self, r):
        self.r, self.seen = r, 0

    def __call__(self, points, joints, state):
        self.seen += points.shape[0]
        return points.norm(dim=-1) < self.r


def test_per_joint_rejection_with_two_criteria_accepts_their_conjunction():
    """Every accepted joint passes both criteria; the second is only asked about the points the
    first passed; acceptance rate of the conjunction from the accepted fraction."""
    sk = human31()
    plane, ball = _BeyondPlane(0.0), _InBall(1.5)
    prop = SpatialPriorProposal(sk, criteria=[plane, ball], max_tries=64)
    L = prop.joint_index.numel()
    g = torch.Generator().manual_seed(0)
    P = 400
    mu = torch.zeros(P, L, 3, dtype=torch.float64)
    x = torch.randn(P, L, 3, generator=g, dtype=torch.float64)
    x, tries, failed = prop._reject(x, mu, torch.ones(P, L, 1, dtype=torch.float64),
                                    [(plane, None), (ball, None)], g)
    ok = (x[..., 0] > 0) & (x.norm(dim=-1) < 1.5)
    assert failed == 0 and bool(ok.all())
    # P(x0 > 0 and |x| < 1.5) = P(chi2_3 < 2.25) / 2 = 0.2389 for a standard normal
    p = 0.23892
    assert abs(float(tries.double().mean()) - 1 / p) < 0.05 / p
    assert ball.seen < plane.seen  # the ball only sees what passed the plane


def test_depth_criterion_keeps_joints_near_the_cloud(scene):
    sk, body, rig, th, masks, pts = scene
    frame = Frame(index=0, time=0.0, silhouettes=masks, depth=pts)
    near = NearPointCloud(sk)
    tree = near.prepare(frame)
    g = torch.Generator().manual_seed(2)
    driven = SpatialPriorProposal(sk, position_std=0.08, joints="upper_body",
                                  criteria=[near], max_tries=200)
    out = driven.sample(ProposalContext(th, frame=frame), 200, g)
    assert out.stats["failed_joints"] < 0.01 * 200 * driven.joint_index.numel()
    # before the projection every drawn joint satisfied its radius: the projected ones are
    # close to the cloud too (the projection moves joints by centimetres)
    pos = sk(out.particles).positions[:, driven.joint_index]
    d, _ = tree.query(pos.reshape(-1, 3).double().numpy())
    r = near.radius[driven.joint_index].repeat(200).numpy()
    assert float((d < r + 0.05).mean()) > 0.95
    assert near.prepare(Frame(index=0, time=0.0, depth=torch.zeros(0, 3))) is None
    with pytest.raises(ValueError, match="radii.l_hand"):
        NearPointCloud(sk, radii={"l_hand": -1.0})


def test_regression_frame_data_never_stale(scene, monkeypatch):
    """The criteria's per-frame state (k-d tree, masks) belongs to the frame it was built from.
    It used to be cached under ``id(frame)``, and the tracker's next frame, allocated where the
    freed one lived, often got the same id — and the previous frame's point cloud (tracks
    changed from run to run). Here every object has the same id, as after such a reuse: each
    frame must still see its own cloud (a far one: every joint fails its radius; the body's:
    almost none)."""
    import torchmocap.proposals.spatial as spatial

    monkeypatch.setattr(spatial, "id", lambda obj: 0, raising=False)
    sk, body, rig, th, masks, pts = scene
    driven = SpatialPriorProposal(sk, position_std=0.03, joints="upper_body",
                                  criteria=[NearPointCloud(sk)], max_tries=4)
    L = driven.joint_index.numel()
    g = torch.Generator().manual_seed(5)
    for i in range(4):
        frame = Frame(index=i, time=0.0, depth=pts + (10.0 if i % 2 else 0.0))
        out = driven.sample(ProposalContext(th, frame=frame), 50, g)
        if i % 2:
            assert out.stats["failed_joints"] == 50 * L, i
        else:
            assert out.stats["failed_joints"] < 0.1 * 50 * L, i


def test_whole_pose_rejection_counts_rejections(scene):
    sk, body, rig, th, masks, _ = scene
    frame = Frame(index=0, time=0.0, silhouettes=masks)
    base = AngularPriorProposal(sk, rotation_std_deg=15.0, joints="upper_body")
    rej = RejectionProposal(base, PoseInSilhouette(sk, rig, "upper_body"), max_tries=200000)
    out = rej.sample(ProposalContext(th, frame=frame), 100, torch.Generator().manual_seed(3))
    assert out.stats["filled"] == 1.0 and out.stats["rejections_per_sample"] > 1
    crit = PoseInSilhouette(sk, rig, "upper_body")
    assert bool(crit(out.particles, ProposalContext(th, frame=frame)).all())


def test_point_cloud_energy(scene):
    sk, body, rig, th, masks, pts = scene
    lik = PointCloudLikelihood(body, rig, sigma=0.02, tau=0.01, max_points=500)
    obs = lik.prepare(Frame(index=0, time=0.0, depth=pts))
    assert obs.shape[0] == 500 and lik.evidence(obs) and lik.requires == ("depth",)
    far = th.clone()
    far[sk.dof_index("l_shoulder_abd")] = 0.2
    v = lik.energy(Poses(torch.stack([th, far]), sk), obs)
    assert float(v[0]) < 1e-3 * float(v[1]) + 1e-6  # the true pose explains every point
    # closed form: one point 5 cm in front of a capsule's camera-facing surface
    one = lik.prepare(Frame(index=0, time=0.0, depth=pts[:1] + 0.0))
    assert float(lik.energy(Poses(th[None], sk), one)[0]) == pytest.approx(0.0, abs=1e-3)
    # the truncation caps an outlier's cost at tau / 2 sigma^2
    out = lik.prepare(Frame(index=0, time=0.0, depth=torch.tensor([[5.0, 5.0, 5.0]])))
    assert float(lik.energy(Poses(th[None], sk), out)[0]) == pytest.approx(
        0.01 / (2 * 0.02**2), rel=1e-5)
    empty = lik.prepare(Frame(index=0, time=0.0, depth=torch.zeros(0, 3)))
    assert not lik.evidence(empty)
    with pytest.raises(ValueError, match="sigma"):
        PointCloudLikelihood(body, rig, sigma=0.0)


def test_point_cloud_gradcheck(scene):
    sk, body, rig, th, masks, pts = scene
    from torchmocap.likelihoods import point_cloud_energy

    sk64, body64 = human31().double(), CapsuleBody(human31().double()).double()
    x = th.double()[None].clone().requires_grad_(True)
    P = pts[:20].double() + 0.01

    def f(x):
        return point_cloud_energy(body64.endpoints(sk64(x)), body64.radii, P,
                                  rig.camera_centers()[0].double(), 0.03, 1.0)

    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-4)
    assert math.isfinite(float(f(x.detach())))


def test_speed_gain_widens_the_spread_of_the_joints_that_moved():
    sk = human31()
    a = sk.zero_pose()
    b = a.clone()
    angle = 0.6
    b[sk.dof_index("r_elbow_flex")] = angle  # only the right forearm (wrist, hand) moves
    prop = SpatialPriorProposal(sk, position_std=0.03, joints="upper_body", speed_gain=2.0)
    names = [sk.joint_names[j] for j in prop.joint_index.tolist()]
    past = PreviousFrame(history=torch.stack([a, a, b]))
    std = prop._spread(ProposalContext(b, previous_frame=past))
    # closed form: the wrist turns about the elbow's hinge (perpendicular to the forearm), so
    # it moves by the chord 2 l sin(angle / 2) of the forearm's length l
    pos = sk(a[None]).positions[0]
    fore = float((pos[sk.joint_index("r_wrist")] - pos[sk.joint_index("r_elbow")]).norm())
    chord = 2 * fore * math.sin(angle / 2)
    i = names.index("r_wrist")
    assert float(std[i]) == pytest.approx(math.hypot(0.03, 2.0 * chord), rel=1e-4)
    assert float(std[names.index("r_hand")]) > float(std[i])
    still = [k for k, n in enumerate(names) if n not in ("r_wrist", "r_hand")]
    assert torch.allclose(std[still], torch.full((len(still),), 0.03), atol=1e-6)
    # no history of two estimates (the first frame), or no gain: the fixed spread
    for ctx, gain in [(ProposalContext(b, previous_frame=PreviousFrame(history=b[None])), 2.0),
                      (ProposalContext(b), 2.0),
                      (ProposalContext(b, previous_frame=PreviousFrame(
                          history=torch.stack([a, b]))), 0.0)]:
        p = SpatialPriorProposal(sk, position_std=0.03, joints="upper_body", speed_gain=gain)
        assert torch.equal(p._spread(ctx), p.std)


def test_speed_gain_draws_scatter_the_moving_hand_wider():
    sk = human31()
    a = sk.zero_pose()
    a[sk.dof_index("l_shoulder_abd")] = 0.5
    b = a.clone()
    b[sk.dof_index("r_elbow_flex")] = 0.8
    ctx = ProposalContext(b, previous_frame=PreviousFrame(history=torch.stack([a, b])))

    def spread(gain, joint):
        p = SpatialPriorProposal(sk, position_std=0.02, joints="upper_body", speed_gain=gain)
        x = p.sample(ctx, 400, torch.Generator().manual_seed(1)).particles
        j = sk.joint_index(joint)
        return float((sk(x).positions[:, j] - sk(b[None]).positions[0, j]).norm(dim=-1).median())

    # the right hand moved ~20 cm in the last frame: its cloud widens several-fold; the left
    # hand did not move: its cloud stays (up to what the projection couples through the chest)
    assert spread(1.0, "r_hand") > 3 * spread(0.0, "r_hand")
    assert spread(1.0, "l_hand") < 1.3 * spread(0.0, "l_hand")


@pytest.mark.parametrize("gain", [-0.1, float("nan"), float("inf"), True, "1"])
def test_speed_gain_rejects_bad_values(gain):
    with pytest.raises(ValueError, match="speed_gain"):
        SpatialPriorProposal(human31(), speed_gain=gain)
