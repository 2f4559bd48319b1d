"""Closed-form and iterative limb inverse kinematics (Sminchisescu & Triggs §3.1-3.2)."""

from __future__ import annotations

import doctest
import importlib
import math

import numpy as np
import pytest
import torch

from torchmocap.cameras import CameraRig, look_at
from torchmocap.geometry import so3_log
from torchmocap.geometry.subproblems import three_axis_rotation
from torchmocap.ik import (
    HUMAN31_LIMBS,
    LimbIK,
    LimbSpec,
    interpretation_tree,
    limb_dofs,
    solve_limb,
)
from torchmocap.skeleton import human31, upper_body

F64 = torch.float64
LIMBS = list(HUMAN31_LIMBS)
limb_module = importlib.import_module("torchmocap.ik.limb")


@pytest.fixture(scope="module")
def sk():
    return human31().double()


@pytest.fixture(scope="module")
def ub():
    return upper_body().double()


def _poses(sk, n: int, gen: torch.Generator, margin: float = 0.0) -> torch.Tensor:
    """Uniform random poses inside the joint limits (shrunk by ``margin`` radians)."""
    lo, hi = sk.lower.double().clone(), sk.upper.double().clone()
    lo[torch.isinf(lo)], hi[torch.isinf(hi)] = -math.pi, math.pi
    lo, hi = lo + margin, hi - margin
    th = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=gen, dtype=F64)
    if sk.root_translation:
        th[:, :3] = 0.2 * torch.randn(n, 3, generator=gen, dtype=F64)
    return th


def _targets(sk, theta, limb, M=None):
    spec = HUMAN31_LIMBS[limb] if isinstance(limb, str) else limb
    names = spec.targets[:M] if M else spec.targets
    return sk(theta).positions[..., [sk.joint_index(j) for j in names], :]


def _with_limb(theta, other, dofs):
    out = theta.clone()
    out[..., dofs] = other[..., dofs]
    return out


def _rig(eye, target) -> CameraRig:
    R, t = look_at(eye.double(), target.double())
    K = torch.tensor([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]], dtype=F64)
    return CameraRig(K[None], R[None], t[None], (640, 480))


class TestSolveLimb:
    def test_smoke(self, sk, device):
        skd = sk.to(device)
        th = torch.zeros(3, sk.num_dofs, dtype=F64, device=device)
        th[:, sk.dof_index("l_elbow_flex")] = 0.7
        r = solve_limb(skd, th, "l_arm", _targets(skd, th, "l_arm"))
        assert r.theta.shape == (3, sk.num_dofs) and r.theta.device == th.device
        for f in (r.within_limits, r.reachable, r.straight, r.iterative):
            assert f.shape == (3,) and f.dtype == torch.bool
        assert float(r.residual.max()) < 1e-12
        assert bool(r.within_limits.all() & r.reachable.all())

    @pytest.mark.parametrize("limb", LIMBS)
    def test_cardinality(self, sk, limb):
        g = torch.Generator().manual_seed(0)
        th = _poses(sk, 6, g).reshape(2, 3, -1)
        tg = _targets(sk, th, limb)
        r = solve_limb(sk, th, limb, tg)
        assert r.theta.shape == (2, 3, sk.num_dofs) and r.residual.shape == (2, 3)
        # one pose, many target sets (broadcast), and the two-target form
        r2 = solve_limb(sk, th[0, 0], limb, tg[0, :, :2])
        assert r2.theta.shape == (3, sk.num_dofs)
        assert len(limb_dofs(sk, limb)) == (6 if "leg" in limb else 4)

    @pytest.mark.parametrize("method", ["closed_form", "auto"])
    @pytest.mark.parametrize("model, limb", [("sk", "r_leg"), ("sk", "l_arm"),
                                             ("ub", "r_arm")])
    def test_feature_broadcast_pose_equals_the_expanded_call(self, request, model, limb,
                                                             method):
        """One pose per row broadcast over several target sets ``(B, 1, D)`` x ``(B, L, M, 3)``
        (the leaves of an interpretation tree: the frame above the limb is posed once per row)
        gives exactly the result of the expanded ``(B * L, D)`` call, and the reported residual
        is the distance of the fully posed skeleton's limb joints from the targets."""
        sk = request.getfixturevalue(model)
        g = torch.Generator().manual_seed(3)
        B, L = 4, 5
        th = _poses(sk, B, g)
        tg = _targets(sk, _poses(sk, B * L, g), limb).reshape(B, L, -1, 3)
        tg = tg - tg[:, :, :1] + _targets(sk, th, limb)[:, None, :1]  # reachable-ish
        a = solve_limb(sk, th[:, None], limb, tg, method=method)
        b = solve_limb(sk, th[:, None].expand(B, L, -1).reshape(B * L, -1), limb,
                       tg.reshape(B * L, -1, 3), method=method)
        assert a.theta.shape == (B, L, sk.num_dofs)
        assert torch.equal(a.theta.reshape(B * L, -1), b.theta)
        assert torch.equal(a.residual.reshape(-1), b.residual)
        assert torch.equal(a.within_limits.reshape(-1), b.within_limits)
        pos = _targets(sk, a.theta, limb)
        assert torch.allclose((pos - tg).norm(dim=-1).amax(-1), a.residual, atol=1e-12)

    @pytest.mark.parametrize("limb", LIMBS)
    def test_feature_closed_form_recovers_random_poses(self, sk, limb):
        """Positions to ~1e-12 m and angles exactly, from a *different* reference pose (the
        in-limit candidate is unique for human31's limits)."""
        g = torch.Generator().manual_seed(1)
        n = 1000
        truth = _poses(sk, n, g)
        dofs = limb_dofs(sk, limb)
        start = _with_limb(truth, _poses(sk, n, g), dofs)
        r = solve_limb(sk, start, limb, _targets(sk, truth, limb), method="closed_form")
        assert float(r.residual.max()) < 1e-9
        assert bool(r.within_limits.all() & r.reachable.all())
        assert not bool(r.iterative.any())
        assert float((r.theta - truth).abs().max()) < 1e-8
        # everything above the limb is untouched
        keep = [d for d in range(sk.num_dofs) if d not in dofs]
        assert torch.equal(r.theta[:, keep], start[:, keep])

    @pytest.mark.parametrize("limb", ["l_arm", "r_arm"])
    def test_feature_closed_form_two_dof_wrist(self, ub, limb):
        """upper_body's arm is the paper's 3-link limb (shoulder 3, elbow 1, wrist 2)."""
        g = torch.Generator().manual_seed(2)
        truth = _poses(ub, 1000, g)
        start = _with_limb(truth, _poses(ub, 1000, g), limb_dofs(ub, limb))
        r = solve_limb(ub, start, limb, _targets(ub, truth, limb), method="closed_form")
        assert float(r.residual.max()) < 1e-9
        assert float((r.theta - truth).abs().max()) < 1e-8

    def test_feature_without_tip_keeps_reference_end(self, sk):
        g = torch.Generator().manual_seed(3)
        truth = _poses(sk, 200, g)
        start = _with_limb(truth, _poses(sk, 200, g), limb_dofs(sk, "r_leg"))
        r = solve_limb(sk, start, "r_leg", _targets(sk, truth, "r_leg", M=2))
        ankle = sk.joint_dofs("r_ankle")
        assert torch.equal(r.theta[:, ankle], start[:, ankle])
        assert float(r.residual.max()) < 1e-9  # knee and ankle positions

    def test_feature_straight_limb_keeps_reference_twist(self, sk):
        """A straight elbow leaves the shoulder twist unobservable: positions are reproduced,
        ``straight`` is set, and the shoulder differs from the reference by a pure swing
        (a rotation about an axis orthogonal to the arm)."""
        g = torch.Generator().manual_seed(4)
        n = 300
        truth = _poses(sk, n, g, margin=0.05)
        truth[:, sk.dof_index("l_elbow_flex")] = 0.0
        dofs = limb_dofs(sk, "l_arm")
        # reference = truth: angles come back exactly
        r = solve_limb(sk, truth, "l_arm", _targets(sk, truth, "l_arm"), method="closed_form")
        assert bool(r.straight.all())
        assert float((r.theta - truth).abs().max()) < 1e-9
        # another reference: positions exact, relative shoulder rotation is twist-free
        ref = _with_limb(truth, _poses(sk, n, g, margin=0.05), dofs)
        r = solve_limb(sk, ref, "l_arm", _targets(sk, truth, "l_arm"), method="closed_form")
        assert bool(r.straight.all()) and float(r.residual.max()) < 1e-9
        axes = torch.tensor(sk.joint_axes[sk.joint_index("l_shoulder")], dtype=F64)
        sh = sk.joint_dofs("l_shoulder")
        L_ref = three_axis_rotation(axes.expand(n, 3, 3), ref[:, sh])
        L_sol = three_axis_rotation(axes.expand(n, 3, 3), r.theta[:, sh])
        bone_ref = L_ref @ torch.tensor([0.0, 0.0, -1.0], dtype=F64)
        w = so3_log(L_sol @ L_ref.transpose(-1, -2))
        assert float((w * bone_ref).sum(-1).abs().max()) < 1e-9
        # power: the solution is not the reference itself
        assert float(w.norm(dim=-1).median()) > 0.1

    def test_feature_out_of_reach_gives_stretched_limb(self, sk):
        """Targets beyond the limb length: ``reachable`` is False, the closed form is the
        straight arm pointing at the end target (the closest any pose gets the wrist to it)."""
        g = torch.Generator().manual_seed(5)
        n = 200
        th = _poses(sk, n, g)
        kin = sk(th)
        sh = kin.positions[:, sk.joint_index("l_shoulder")]
        dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=-1)
        reach = float(sk.offsets[sk.joint_index("l_elbow")].norm()
                      + sk.offsets[sk.joint_index("l_wrist")].norm())  # ~0.54 m
        dist = 0.6 + 0.5 * torch.rand(n, generator=g, dtype=F64)
        wrist_t = sh + dist[:, None] * dirs
        elbow_t = sh + 0.29 * torch.nn.functional.normalize(
            dirs + 0.3 * torch.randn(n, 3, generator=g, dtype=F64), dim=-1)
        tg = torch.stack([elbow_t, wrist_t], 1)
        r = solve_limb(sk, th, "l_arm", tg, method="closed_form")
        assert not bool(r.reachable.any())
        assert float(r.theta[:, sk.dof_index("l_elbow_flex")].abs().max()) < 1e-9
        assert bool(r.straight.all())
        wrist = sk(r.theta).positions[:, sk.joint_index("l_wrist")]
        torch.testing.assert_close(wrist, sh + reach * dirs, rtol=0, atol=1e-12)
        assert float(((wrist - wrist_t).norm(dim=-1) - (dist - reach)).abs().max()) < 1e-12
        # auto may trade wrist error for elbow error, never for a worse total (unless the
        # stretched arm violated a limit: then it moves into the limits first)
        a = solve_limb(sk, th, "l_arm", tg, method="auto")
        assert not bool(a.reachable.any()) and bool(a.within_limits.all())
        inside = r.within_limits
        assert 0 < int(inside.sum()) < n

        def sse(t):
            e = sk(t).positions[:, [sk.joint_index("l_elbow"), sk.joint_index("l_wrist")]] - tg
            return (e * e).sum((-1, -2))

        assert bool((sse(a.theta) <= sse(r.theta) + 1e-12)[inside].all())
        assert float(sse(a.theta)[inside].mean()) < float(sse(r.theta)[inside].mean())

    def test_feature_fallback_respects_limits_and_minimises(self, sk):
        """Targets generated with the shoulder rotated beyond its internal-rotation limit: for
        most of them every exact solution violates a limit. There ``auto`` returns a pose
        within limits that is a constrained minimum of the joint-position error (checked
        against scipy's L-BFGS-B from many starts); elsewhere it keeps the exact in-limit
        closed form (the other 3-axis decomposition)."""
        from scipy.optimize import minimize

        g = torch.Generator().manual_seed(6)
        n = 16
        truth = _poses(sk, n, g, margin=0.2)
        d_int = sk.dof_index("l_shoulder_int")
        truth[:, d_int] = float(sk.upper[d_int]) + 0.4 + 0.3 * torch.rand(n, generator=g,
                                                                          dtype=F64)
        truth[:, sk.dof_index("l_elbow_flex")] = 1.0 + torch.rand(n, generator=g, dtype=F64)
        tg = _targets(sk, truth, "l_arm")
        start = sk.clamp(truth)
        cf = solve_limb(sk, start, "l_arm", tg, method="closed_form")
        assert float(cf.residual.max()) < 1e-9
        out = ~cf.within_limits
        assert int(out.sum()) >= n // 2
        a = solve_limb(sk, start, "l_arm", tg, method="auto")
        assert bool(a.within_limits.all())
        assert torch.equal(a.iterative, out)
        assert torch.equal(a.theta[~out], cf.theta[~out])
        assert float(a.residual[out].min()) > 1e-3  # the limit costs accuracy
        dofs = limb_dofs(sk, "l_arm")
        assert dofs == list(range(dofs[0], dofs[-1] + 1))  # contiguous
        lo, hi = sk.lower[dofs].numpy(), sk.upper[dofs].numpy()
        joints = [sk.joint_index(j) for j in HUMAN31_LIMBS["l_arm"].targets]
        rs = np.random.default_rng(0)
        for i in out.nonzero()[:, 0].tolist()[:6]:
            def cost(x, i=i):
                xt = torch.as_tensor(x).requires_grad_()
                t = torch.cat([start[i, : dofs[0]], xt, start[i, dofs[-1] + 1:]])
                c = ((sk(t).positions[joints] - tg[i]) ** 2).sum()
                c.backward()
                return float(c.detach()), xt.grad.numpy()

            mine = cost(a.theta[i, dofs].numpy())[0]
            best = min(minimize(cost, rs.uniform(lo, hi), jac=True, method="L-BFGS-B",
                                bounds=list(zip(lo, hi))).fun for _ in range(10))
            assert mine <= best + 1e-9

    def test_feature_iterative_method(self, sk):
        g = torch.Generator().manual_seed(7)
        truth = _poses(sk, 100, g, margin=0.1)
        dofs = limb_dofs(sk, "r_leg")
        start = truth.clone()
        start[:, dofs] += 0.05 * torch.randn(100, len(dofs), generator=g, dtype=F64)
        r = solve_limb(sk, sk.clamp(start), "r_leg", _targets(sk, truth, "r_leg"),
                       method="iterative")
        assert bool(r.iterative.all() & r.within_limits.all())
        assert float(r.residual.max()) < 1e-8

    def test_feature_float32(self):
        sk32 = human31()
        g = torch.Generator().manual_seed(8)
        truth = _poses(sk32, 2000, g).float()
        for limb in ("l_arm", "r_leg"):
            tg = _targets(sk32, truth, limb)
            cf = solve_limb(sk32, truth, limb, tg, method="closed_form")
            assert cf.theta.dtype == torch.float32
            assert float(cf.residual.median()) < 1e-6
            # near full extension the distance hardly depends on the hinge angle
            assert float(cf.residual.max()) < 5e-4
            a = solve_limb(sk32, truth, limb, tg)
            assert float(a.residual.max()) < 1e-5 and bool(a.within_limits.all())

    def test_feature_limb_jacobian_matches_skeleton(self, sk, ub):
        """The iterative solver's limb Jacobian is the skeleton's analytic one restricted to
        the limb's DoFs (and its forward kinematics the skeleton's)."""
        g = torch.Generator().manual_seed(9)
        for skel, limbs in ((sk, LIMBS), (ub, ["l_arm", "r_arm"])):
            th = _poses(skel, 20, g)
            kin, Jp, _ = skel.jacobian(th)
            for limb in limbs:
                plan = limb_module._plan(skel, limb)
                R_par = kin.rotations[:, plan.parent]
                p_root = kin.positions[:, plan.root]
                P, J = limb_module._limb_forward(plan, R_par, p_root, th[:, plan.dofs],
                                                 len(plan.target_joints), True)
                jj = plan.target_joints
                torch.testing.assert_close(P, kin.positions[:, jj], rtol=0, atol=1e-12)
                torch.testing.assert_close(J, Jp[:, jj][..., plan.dofs], rtol=0, atol=1e-12)

    @pytest.mark.parametrize(("skeleton", "limb", "K"),
                             [("human31", "l_arm", 2), ("human31", "r_leg", 3),
                              ("upper_body", "r_arm", 3)])
    def test_feature_flip_tree_then_ik(self, sk, ub, skeleton, limb, K):
        """Flip a limb of a random pose as seen from a camera, solve the IK of every leaf: the
        forward kinematics of the result projects the limb's joints onto the original image
        points (every valid leaf for the arms; human31's ankle reaches a flipped toe only for
        some leaves — those are flagged not reachable)."""
        skel = sk if skeleton == "human31" else ub
        g = torch.Generator().manual_seed(10)
        n = 200
        th = _poses(skel, n, g)
        spec = HUMAN31_LIMBS[limb]
        names = (spec.root,) + spec.targets[:K]
        idx = [skel.joint_index(j) for j in names]
        pos = skel(th).positions[:, idx]
        rig = _rig(torch.tensor([0.8, -4.0, 1.7]), torch.tensor([0.0, 0.0, 1.0]))
        tree = interpretation_tree(pos, rig.camera_centers()[0])
        L = 2**K
        th_rep = th[:, None].expand(n, L, -1).reshape(n * L, -1)
        r = solve_limb(skel, th_rep, limb, tree.positions[:, :, 1:].reshape(n * L, K, 3),
                       method="closed_form")
        valid = tree.valid.reshape(-1)
        ok = valid & r.reachable
        if skeleton == "upper_body" or K == 2:
            assert bool(ok[valid].all())
        else:
            assert 0.4 < float(ok.double().sum() / valid.double().sum()) < 0.9
        fk = skel(r.theta).positions[:, idx]
        pix = rig.project(fk)[0][:, 0]
        pix0 = rig.project(pos)[0][:, 0].repeat_interleave(L, 0)
        assert float((pix - pix0).abs().amax((-1, -2))[ok].max()) < 1e-6
        assert float(r.residual[ok].max()) < 1e-9
        # power: the flipped solutions really are other poses
        moved = (fk - pos.repeat_interleave(L, 0)).norm(dim=-1).amax(-1)
        assert float(moved[ok].max()) > 0.2
        # and they can be pruned by joint limits afterwards
        keep = ok & r.within_limits
        assert 0 < int(keep.sum()) < int(ok.sum())

    def test_exception(self, sk):
        th = torch.zeros(2, sk.num_dofs, dtype=F64)
        tg = _targets(sk, th, "l_arm")
        with pytest.raises(KeyError, match="limb"):
            solve_limb(sk, th, "tail", tg)
        with pytest.raises(ValueError, match="root"):
            solve_limb(sk, th, LimbSpec("l_elbow", "l_wrist", "l_hand"), tg)
        with pytest.raises(ValueError, match="hinge"):
            solve_limb(sk, th, LimbSpec("l_shoulder", "l_wrist", "l_hand"), tg)
        with pytest.raises(ValueError, match="targets"):
            solve_limb(sk, th, "l_arm", tg[:, :1])
        with pytest.raises(ValueError, match="targets"):
            solve_limb(sk, th, "l_arm", torch.zeros(2, 4, 3, dtype=F64))
        with pytest.raises(ValueError, match="targets"):
            solve_limb(sk, th, "l_arm", torch.full_like(tg, math.nan))
        with pytest.raises(ValueError, match="theta"):
            solve_limb(sk, torch.zeros(2, 30, dtype=F64), "l_arm", tg)
        with pytest.raises(ValueError, match="method"):
            solve_limb(sk, th, "l_arm", tg, method="newton")
        with pytest.raises(ValueError, match="reference"):
            solve_limb(sk, th, "l_arm", tg, reference=torch.full_like(th, math.inf))
        with pytest.raises(TypeError, match="skeleton"):
            solve_limb(None, th, "l_arm", tg)

    @pytest.mark.parametrize("same_reference", [True, False])
    def test_gradcheck(self, sk, same_reference):
        """The closed form is differentiable in the targets (away from straight limbs), also
        where the swing from the reference is the identity."""
        g = torch.Generator().manual_seed(11)
        truth = _poses(sk, 3, g, margin=0.3)
        dofs = limb_dofs(sk, "l_leg")
        th = truth if same_reference else _with_limb(truth, _poses(sk, 3, g, margin=0.3), dofs)
        tg = _targets(sk, truth, "l_leg").requires_grad_()
        assert torch.autograd.gradcheck(
            lambda t: solve_limb(sk, th, "l_leg", t, method="closed_form").theta[:, dofs],
            (tg,))


class TestLimbIK:
    def test_module(self, sk):
        g = torch.Generator().manual_seed(12)
        th = _poses(sk, 50, g)
        tg = _targets(sk, th, "r_arm")
        ik = LimbIK(sk, "r_arm", method="closed_form")
        a, b = ik(th, tg), solve_limb(sk, th, "r_arm", tg, method="closed_form")
        assert torch.equal(a.theta, b.theta) and torch.equal(a.residual, b.residual)
        assert ik.dofs == limb_dofs(sk, "r_arm")
        assert "r_shoulder" in repr(ik)
        with pytest.raises(ValueError, match="method"):
            LimbIK(sk, "r_arm", method="x")


def test_rotation_helpers_used_by_the_solver():
    """The swing helper takes unit x to unit y, including opposite vectors."""
    g = torch.Generator().manual_seed(13)
    x = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=F64), dim=-1)
    y = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=F64), dim=-1)
    y[:10] = -x[:10]
    # nearly opposite and nearly equal: a 1e-9 rad swing away from -x / from x
    perp = torch.nn.functional.normalize(torch.linalg.cross(x, y), dim=-1)
    y[10:20] = -x[10:20] * math.cos(1e-9) + perp[10:20] * math.sin(1e-9)
    y[20:30] = x[20:30] * math.cos(1e-9) + perp[20:30] * math.sin(1e-9)
    R = limb_module._swing(x, y)
    torch.testing.assert_close((R @ x[..., None])[..., 0], y, rtol=0, atol=1e-12)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(500, 3, 3),
                               rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(500, dtype=F64), rtol=0,
                               atol=1e-12)
    # minimal: the rotation axis is orthogonal to both vectors, the angle is theirs
    w = so3_log(R[10:])
    assert float((w * x[10:]).sum(-1).abs().max()) < 1e-10
    ang = torch.atan2(torch.linalg.cross(x, y).norm(dim=-1), (x * y).sum(-1))
    torch.testing.assert_close(w.norm(dim=-1), ang[10:], rtol=0, atol=1e-12)


def test_docstring_examples():
    res = doctest.testmod(limb_module, extraglobs={"torch": torch})
    assert res.attempted > 0 and res.failed == 0
