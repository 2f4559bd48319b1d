"""Kinematic jump sampling: flipped limbs keep the image and the bone lengths, the jumps of a
synthetic monocular pose are distinct zero-cost minima of the 2D-joint energy, covariance
voting, the proposal's contract (exactly num samples, statistics, a CSS base)."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.filters.optim import distinct_minima, levenberg_marquardt
from torchmocap.likelihoods import FrameEnergy, Joints2DLikelihood, Poses
from torchmocap.proposals import (
    CovarianceScaledProposal,
    KinematicJumpProposal,
    ProposalContext,
    chain_votes,
    kinematic_jumps,
    limb_flips,
    parse_chain,
)
from torchmocap.skeleton import human31

LIMBS = ["l_arm", "r_arm", "l_leg", "r_leg"]
#: a monocular pose with bent arms and legs, turned 30 deg from the camera
POSE_DEG = {"pelvis_rz": 30, "spine_flex": 10, "l_hip_flex": 11, "l_knee_flex": 60,
            "l_hip_abd": -16, "l_hip_int": 16, "l_ankle_dorsi": -29, "l_ankle_inv": -6,
            "r_hip_flex": 19, "r_knee_flex": 69, "r_hip_abd": -3, "r_hip_int": 2,
            "r_ankle_dorsi": -3, "r_ankle_inv": 12, "l_shoulder_flex": 50, "l_shoulder_abd": 30,
            "l_elbow_flex": 60, "r_shoulder_flex": 20, "r_shoulder_abd": 40, "r_elbow_flex": 70}
NO_HANDS = ["pelvis", "spine", "neck", "head", "head_top", "l_shoulder", "l_elbow", "l_wrist",
            "r_shoulder", "r_elbow", "r_wrist", "l_hip", "l_knee", "l_ankle", "l_toe", "r_hip",
            "r_knee", "r_ankle", "r_toe"]


@pytest.fixture(scope="module")
def mono():
    sk = human31().double()
    rig = make_ring_rig(1, radius=4.5, height=1.5, image_size=(640, 480), fov_deg=55.0)
    th = sk.zero_pose()
    for k, v in POSE_DEG.items():
        th[sk.dof_index(k)] = math.radians(v)
    return sk, rig, th


def _tree_limb_joints(sk, limb):
    return {"l_arm": ["l_shoulder", "l_elbow", "l_wrist"],
            "r_arm": ["r_shoulder", "r_elbow", "r_wrist"],
            "l_leg": ["l_hip", "l_knee", "l_ankle", "l_toe"],
            "r_leg": ["r_hip", "r_knee", "r_ankle", "r_toe"]}[limb]


class TestLimbFlips:
    @pytest.mark.parametrize("limb", LIMBS)
    def test_feature_flips_keep_the_image_and_the_bone_lengths(self, mono, limb):
        sk, rig, th = mono
        c = rig.camera_centers()[0]
        f = limb_flips(sk, th[None], limb, c)
        names = _tree_limb_joints(sk, limb)
        idx = [sk.joint_index(n) for n in names]
        assert f.joints == idx and f.flips.shape == (2 ** (len(idx) - 1), len(idx) - 1)
        assert bool(f.kept[0, 0]) and torch.equal(f.theta[0, 0], th)
        kept = f.kept[0]
        assert int(kept.sum()) >= 2  # this pose has real flips on every limb
        poses = f.theta[0, kept]
        pos = sk(poses).positions
        pos0 = sk(th).positions
        pix = rig.project(pos)[0][:, 0]  # (L, J, 2)
        pix0 = rig.project(pos0)[0][0]
        # the tree's joints project where the mode's do (before any optimisation)
        assert torch.allclose(pix[:, idx], pix0[idx].expand(len(poses), -1, -1), atol=1e-6)
        # and sit at the leaves' positions: the IK reproduced them
        assert torch.allclose(pos[:, idx], f.positions[0, kept], atol=1e-8)
        # bone lengths of the (valid) leaves equal the model's
        L = (f.positions[0, :, 1:] - f.positions[0, :, :-1]).norm(dim=-1)
        ref = (pos0[idx[1:]] - pos0[idx[:-1]]).norm(dim=-1)
        assert torch.allclose(L[f.valid[0]], ref.expand_as(L)[f.valid[0]], atol=1e-9)
        # flipped leaves really move in depth, joints outside the limb stay
        others = [j for j in range(sk.num_joints) if j not in idx
                  and sk.joint_names[j] not in ("l_hand", "r_hand")]
        assert torch.allclose(pos[:, others], pos0[others].expand(len(poses), -1, -1),
                              atol=1e-9)
        moved = (pos[1:, idx] - pos0[idx]).norm(dim=-1).amax(-1)
        assert bool((moved > 0.03).all())
        # kept leaves are inside the joint limits
        assert bool(sk.within_limits(poses, tol=1e-9).all())

    @pytest.mark.parametrize("limb", LIMBS)
    def test_min_flip_drops_exactly_the_near_tangent_leaves(self, mono, limb):
        """With ``min_flip`` a leaf survives iff every flip it makes moves its child joint by at
        least that much against the leaf without that flip (checked leaf by leaf); 0 changes
        nothing; the unflipped pose is always kept."""
        sk, rig, th = mono
        c = rig.camera_centers()[0]
        base = limb_flips(sk, th[None], limb, c)
        moves = []
        for i in range(base.flips.shape[0]):
            for k in range(base.flips.shape[1]):
                if base.flips[i, k] and base.valid[0, i]:
                    moves.append(float((base.positions[0, i, k + 1]
                                        - base.positions[0, i ^ (1 << k), k + 1]).norm()))
        thr = sorted(moves)[len(moves) // 2]  # drops about half of the flipped links
        f = limb_flips(sk, th[None], limb, c, min_flip=thr)
        for i in range(base.flips.shape[0]):
            ok = all(float((base.positions[0, i, k + 1]
                            - base.positions[0, i ^ (1 << k), k + 1]).norm()) >= thr
                     for k in range(base.flips.shape[1]) if base.flips[i, k])
            assert bool(f.kept[0, i]) == (bool(base.kept[0, i]) and (ok or i == 0))
        assert int(f.kept.sum()) < int(base.kept.sum())
        assert torch.equal(limb_flips(sk, th[None], limb, c, min_flip=0.0).kept, base.kept)
        with pytest.raises(ValueError, match="min_flip"):
            limb_flips(sk, th[None], limb, c, min_flip=-1.0)

    def test_feature_link_subsets(self, mono):
        sk, rig, th = mono
        c = rig.camera_centers()[0]
        full = limb_flips(sk, th[None], "l_leg", c)
        sub = limb_flips(sk, th[None], "l_leg:1,2", c)
        assert sub.flips.shape == (4, 3) and not bool(sub.flips[:, 0].any())
        rows = [int(sum(int(b) << k for k, b in enumerate(r))) for r in sub.flips.tolist()]
        assert torch.allclose(sub.theta[0], full.theta[0, rows])
        assert parse_chain({"limb": "l_leg", "links": [1, 2]}) == parse_chain("l_leg:1,2")
        assert parse_chain("l_leg:1,2").name == "l_leg:1,2"


class TestKinematicJumps:
    def test_feature_jumps_are_distinct_zero_cost_minima(self, mono):
        """KJS on a synthetic monocular pose: every kept combination of limb flips is a
        distinct minimum of the 2D-joint energy with (near-)zero cost — already before
        optimisation (hands excluded: the human31 hand is rigid on the forearm)."""
        sk, rig, th = mono
        c = rig.camera_centers()[0]
        jumps = kinematic_jumps(sk, th, LIMBS, c)
        assert jumps.leaves == 4 * 4 * 8 * 8 and jumps.kept >= 100
        assert torch.equal(jumps.theta[0], th) and not bool(jumps.flips[0].any())
        pix = rig.project(sk(th).positions)[0][0]
        obs = torch.cat([pix, torch.ones(21, 1, dtype=torch.float64)], -1)[None]
        term = Joints2DLikelihood(rig, skeleton=sk, joints=NO_HANDS, scale_px=2.0)
        o = term.prepare(Frame(index=0, time=0.0, joints2d=obs))
        V = FrameEnergy(term, o, sk)
        v0 = V(jumps.theta)
        assert float(v0.max()) < 1e-12  # the samples already sit at the minima
        x, v, _, _, _ = levenberg_marquardt(
            lambda x, rows: term.gauss_newton(Poses(x, sk), o), jumps.theta, sk.lower,
            sk.upper, 20)
        assert float(v.max()) < 1e-12
        assert float((x - jumps.theta).abs().max()) < 1e-6
        # distinct: each pair of minima has a joint more than 2 cm apart, and their parameters
        # differ by more than 0.1 rad
        pos = sk(x).positions
        assert len(distinct_minima(pos, v, 0.02)) == jumps.kept
        assert len(distinct_minima(x, v, 0.1)) == jumps.kept
        # the true pose is one of them, the others are its mirror configurations
        d = (pos - sk(th).positions).norm(dim=-1).amax(-1)
        assert float(d[0]) < 1e-9 and bool((d[1:] > 0.02).all())

    def test_exception(self, mono):
        sk, rig, th = mono
        c = rig.camera_centers()[0]
        with pytest.raises(ValueError, match="each limb at most once"):
            kinematic_jumps(sk, th, ["l_leg", "l_leg:1"], c)
        with pytest.raises(KeyError, match="unknown limb"):
            limb_flips(sk, th[None], "tail", c)
        with pytest.raises(ValueError, match="links"):
            limb_flips(sk, th[None], "l_arm:5", c)


class TestChainVotes:
    def test_feature_votes_of_a_diagonal_covariance(self):
        dofs = [[0, 1], [2], [3, 4, 5]]
        std = torch.tensor([1.0, 2.0, 5.0, 0.1, 0.1, 0.1], dtype=torch.float64)
        v = chain_votes(torch.diag(std**2), dofs)
        assert torch.allclose(v, torch.tensor([3.0, 5.0, 0.3], dtype=torch.float64))
        # rotation invariance of the principal-axes form: a rotated pair votes the same total
        R = torch.tensor([[math.cos(0.3), -math.sin(0.3)], [math.sin(0.3), math.cos(0.3)]],
                         dtype=torch.float64)
        C = torch.diag(std**2)
        C[:2, :2] = R @ torch.diag(std[:2] ** 2) @ R.T
        assert chain_votes(C, dofs)[1:].allclose(v[1:])

    def test_feature_the_uncertain_limb_is_selected(self, mono):
        sk, rig, th = mono
        D = sk.num_dofs
        prop = KinematicJumpProposal(sk, rig, chains=LIMBS, select="vote", num_chains=1)
        cov = torch.eye(D, dtype=torch.float64) * 1e-4
        rl = prop.chain_dofs[LIMBS.index("r_leg")]
        cov[rl, rl] = 0.3
        ctx = ProposalContext(previous=th, covariances=cov)
        out = prop.sample(ctx, 16, torch.Generator().manual_seed(0))
        assert out.stats["votes"] == {"r_leg": 1} and out.stats["voted"] == 1
        # every sample differs from the mode in the right leg only
        moved = (out.particles - th).abs() > 1e-9
        others = [d for d in range(D) if d not in rl]
        assert not bool(moved[:, others].any())


class TestKinematicJumpProposal:
    def test_smoke(self, mono):
        sk, rig, th = mono
        prop = KinematicJumpProposal(sk, rig, chains=LIMBS, select="all")
        out = prop.sample(ProposalContext(previous=th), 50, torch.Generator().manual_seed(0))
        assert out.particles.shape == (50, sk.num_dofs)
        s = out.stats
        assert s["leaves"] == 1024 and s["kept"] + s["pruned"] == 1024 and s["unique"] <= 50
        assert s["component"].shape == (50,) and s["jumped"].shape == (50,)

    def test_cardinality_exactly_num(self, mono):
        sk, rig, th = mono
        prop = KinematicJumpProposal(sk, rig, chains=["l_arm"], select="all")
        g = torch.Generator().manual_seed(1)
        few = prop.sample(ProposalContext(previous=th), 10, g)  # 4 leaves, repeated
        assert few.particles.shape == (10, 31) and few.stats["unique"] == 4
        assert torch.equal(few.particles[:4], few.particles[4:8])
        assert int((~few.stats["jumped"]).sum()) == 3  # the unflipped mode, cyclic
        excl = KinematicJumpProposal(sk, rig, chains=["l_arm"], select="all",
                                     include_original=False)
        out = excl.sample(ProposalContext(previous=th), 3, g)
        assert bool(out.stats["jumped"].all()) and out.stats["unique"] == 3

    @pytest.mark.parametrize("include_original", [True, False])
    def test_feature_leaves_are_the_product_of_the_trees_in_order(self, mono, include_original):
        """The vectorised leaf assembly of the proposal (and of :func:`kinematic_jumps`)
        equals an enumeration of the trees' kept leaves by ``itertools.product``, pose for pose
        and in order, for two modes that flip different chain pairs, with and without the
        unflipped combination."""
        sk, rig, th = mono
        D = sk.num_dofs
        th2 = th.clone()
        th2[sk.dof_index("r_elbow_flex")] = 1.2
        th2[sk.dof_index("l_knee_flex")] = 0.4
        modes = torch.stack([th, th2])
        c = rig.camera_centers()[0]
        prop = KinematicJumpProposal(sk, rig, chains=LIMBS, select="vote", num_chains=2,
                                     include_original=include_original)
        cov = torch.eye(D, dtype=torch.float64).expand(2, D, D).clone() * 1e-4
        pairs = (("l_arm", "r_leg"), ("r_arm", "l_leg"))
        for k, pair in enumerate(pairs):
            for limb in pair:
                d = prop.chain_dofs[LIMBS.index(limb)]
                cov[k][d, d] = 0.3
        ctx = ProposalContext(previous=modes, covariances=cov)
        out = prop.sample(ctx, 10_000, torch.Generator().manual_seed(0))
        n = out.stats["unique"]
        got, comp = out.particles[:n], out.stats["component"][:n]
        for k, pair in enumerate(pairs):
            per = [limb_flips(sk, modes[k][None], limb, c) for limb in pair]
            want, flipped = [], []
            for combo in itertools.product(*[p.kept[0].nonzero()[:, 0].tolist() for p in per]):
                if not include_original and not any(combo):
                    continue
                x = modes[k].clone()
                for p, leaf in zip(per, combo):
                    x[p.dofs] = p.theta[0, leaf, p.dofs]
                want.append(x)
                flipped.append(any(combo))
            want = torch.stack(want)
            mine = got[comp == k]
            assert want.shape[0] > 2 and mine.shape == want.shape
            assert torch.equal(mine, want)
            assert out.stats["jumped"][:n][comp == k].tolist() == flipped
            ref = kinematic_jumps(sk, modes[k], list(pair), c,
                                  include_original=include_original)
            assert torch.equal(ref.theta, want) and ref.flips.any(1).tolist() == flipped
        assert out.stats["kept"] == n

    def test_feature_jumps_of_covariance_scaled_samples(self, mono):
        """Fig. 5: CSS samples of two modes, each jumped over its voted chain."""
        sk, rig, th = mono
        D = sk.num_dofs
        th2 = th.clone()
        th2[sk.dof_index("r_knee_flex")] = 0.9
        modes = torch.stack([th, th2])
        cov = torch.eye(D, dtype=torch.float64).expand(2, D, D).clone() * 1e-4
        la = KinematicJumpProposal(sk, rig).chain_dofs[0]
        rl = KinematicJumpProposal(sk, rig).chain_dofs[3]
        cov[0][la, la] = 0.2  # mode 0 is uncertain in the left arm, mode 1 in the right leg
        cov[1][rl, rl] = 0.2
        base = CovarianceScaledProposal(sk, scale=1.0)
        prop = KinematicJumpProposal(sk, rig, base=base)
        ctx = ProposalContext(previous=modes, log_weights=torch.log(torch.tensor([0.5, 0.5])),
                              covariances=cov)
        out = prop.sample(ctx, 120, torch.Generator().manual_seed(2))
        assert out.particles.shape == (120, D)
        assert set(out.stats["votes"]) == {"l_arm", "r_leg"}
        comp = out.stats["component"]
        assert set(comp.tolist()) == {0, 1}
        jumped = out.stats["jumped"]
        assert 0 < int(jumped.sum()) < 120
        # base samples stay within 0.5 mrad of their mode outside the voted limb
        for k, limb_dofs in ((0, la), (1, rl)):
            rows = comp == k
            others = [d for d in range(D) if d not in limb_dofs]
            dev = (out.particles[rows][:, others] - modes[k, others]).abs().amax()
            assert float(dev) < 0.1
        # same seed, same samples
        again = prop.sample(ctx, 120, torch.Generator().manual_seed(2))
        assert torch.equal(again.particles, out.particles)

    def test_exception(self, mono):
        sk, rig, th = mono
        with pytest.raises(ValueError, match="select"):
            KinematicJumpProposal(sk, rig, select="best")
        with pytest.raises(ValueError, match="camera"):
            KinematicJumpProposal(sk, rig, camera=1)
        with pytest.raises(ValueError, match="rig"):
            KinematicJumpProposal(sk, None)
        with pytest.raises(ValueError, match="each limb at most once"):
            KinematicJumpProposal(sk, rig, chains=["l_arm", "l_arm"])
        prop = KinematicJumpProposal(sk, rig)
        with pytest.raises(ValueError, match="num"):
            prop.sample(ProposalContext(previous=th), 0)
        with pytest.raises(ValueError, match="covariances"):
            prop.sample(ProposalContext(previous=th, covariances=torch.eye(3)), 4)
