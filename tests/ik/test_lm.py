"""Batched Levenberg-Marquardt pose fitting."""

from __future__ import annotations

import pytest
import torch

from torchmocap.ik.lm import fit_pose_lm
from torchmocap.skeleton import human31


@pytest.fixture(scope="module")
def sk():
    return human31().double()


def _poses(sk, n, seed, scale=0.4):
    g = torch.Generator().manual_seed(seed)
    th = sk.clamp(torch.randn(n, sk.num_dofs, generator=g, dtype=torch.float64) * scale)
    th[:, :3] = 0.1 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    return th, g


def test_recovers_exact_positions(sk):
    th, g = _poses(sk, 100, 0)
    start = sk.clamp(th + 0.25 * torch.randn(th.shape, generator=g, dtype=torch.float64))
    res = fit_pose_lm(sk, start, sk(th).positions, list(range(sk.num_joints)), iterations=60,
                      prior_weight=1e-5)
    # every pose reaches its targets (joint positions, not angles: twists of straight limbs are
    # unobservable from positions)
    assert res.position_error.max(dim=1).values.quantile(0.95) < 1e-3
    assert res.position_error.mean() < 5e-4
    assert sk.within_limits(res.theta, tol=1e-9).all()


def test_rotation_targets_fix_twist(sk):
    th, g = _poses(sk, 50, 1)
    th[:, sk.dof_index("l_elbow_flex")] = 0.0  # straight elbow: shoulder twist unobservable
    kin = sk(th)
    start = sk.clamp(th + 0.2 * torch.randn(th.shape, generator=g, dtype=torch.float64))
    joints = list(range(sk.num_joints))
    res = fit_pose_lm(sk, start, kin.positions, joints, target_rotations=kin.rotations,
                      rotation_joints=joints, rotation_weight=0.3, iterations=60,
                      prior_weight=1e-6)
    twist = sk.dof_index("l_shoulder_int")
    assert (res.theta[:, twist] - th[:, twist]).abs().max() < 1e-3
    assert res.rotation_error.max() < 1e-3


def test_least_squares_with_noise_is_no_worse_than_truth(sk):
    """From a perturbed start, the fit to noisy targets ends below the cost of the true poses
    (a least-squares optimum fits part of the noise). Starting at the truth, as this test once
    did, made it pass with zero iterations."""
    th, g = _poses(sk, 60, 2)
    target = sk(th).positions + 0.02 * torch.randn(60, sk.num_joints, 3, generator=g,
                                                   dtype=torch.float64)
    start = sk.clamp(th + 0.1 * torch.randn(th.shape, generator=g, dtype=torch.float64))
    res = fit_pose_lm(sk, start, target, list(range(sk.num_joints)), iterations=100,
                      prior_weight=0.0)
    cost_truth = ((sk(th).positions - target) ** 2).sum((1, 2))
    cost_start = ((sk(start).positions - target) ** 2).sum((1, 2))
    cost_fit = (res.position_error ** 2).sum(1)
    assert res.iterations > 0
    assert bool((cost_start > cost_truth).all())  # the start is not already a solution
    assert (cost_fit <= cost_truth + 1e-9).all()
    # 63 residuals, ~30 observable DoF: the optimum removes about half the noise energy
    assert float(cost_fit.mean()) < 0.8 * float(cost_truth.mean())


def test_joint_limits_respected(sk):
    """A target asking for a hyper-extended knee: from a bent knee the fit straightens it and
    stops exactly at the limit (0), not beyond."""
    th = sk.zero_pose((1,))
    knee = sk.dof_index("l_knee_flex")
    th[0, knee] = 1.0
    target = sk(sk.zero_pose((1,))).positions.clone()
    # the ankle in front of the straight knee: reachable only by bending the knee backwards
    k, a = sk.joint_index("l_knee"), sk.joint_index("l_ankle")
    target[0, a] = target[0, k] + torch.tensor([0.0, -0.3, -0.3], dtype=torch.float64)
    res = fit_pose_lm(sk, th, target, list(range(sk.num_joints)), iterations=30)
    assert 0.0 <= float(res.theta[0, knee]) < 1e-6  # at the limit
    assert sk.within_limits(res.theta, tol=1e-9).all()
    before = (sk(th).positions[0, a] - target[0, a]).norm()
    assert float(res.position_error[0, a]) < float(before)


def test_problems_are_independent_of_their_batch(sk):
    """Each problem's fit is the one it gets alone: a problem that converges early leaves the
    batch (it is not iterated further while a harder one goes on), and one that needs more
    iterations is not cut short by its easy neighbours. Rotation targets and a per-problem prior
    included (they follow the problems through the working set)."""
    th, g = _poses(sk, 6, 4)
    kin = sk(th)
    scale = torch.tensor([0.0, 1e-3, 0.05, 0.2, 0.4, 0.6], dtype=torch.float64)[:, None]
    start = sk.clamp(th + scale * torch.randn(th.shape, generator=g, dtype=torch.float64))
    target = kin.positions + 0.01 * torch.randn(kin.positions.shape, generator=g,
                                                dtype=torch.float64)
    joints = list(range(sk.num_joints))
    rj = [sk.joint_index(n) for n in ("l_elbow", "r_knee", "spine")]
    kw = dict(target_rotations=kin.rotations[:, rj], rotation_joints=rj, iterations=80,
              prior_weight=1e-3)
    batch = fit_pose_lm(sk, start, target, joints, **kw)
    alone = [fit_pose_lm(sk, start[i:i + 1], target[i:i + 1], joints,
                         **{**kw, "target_rotations": kin.rotations[i:i + 1, rj]})
             for i in range(6)]
    iters = [a.iterations for a in alone]
    assert min(iters) < max(iters) and batch.iterations == max(iters)
    for i, a in enumerate(alone):
        assert torch.allclose(batch.theta[i], a.theta[0], atol=1e-12, rtol=0), i
        assert torch.allclose(batch.cost[i], a.cost[0], atol=1e-15, rtol=1e-12), i
        assert torch.allclose(batch.rotation_error[i], a.rotation_error[0], atol=1e-12), i


def test_exceptions(sk):
    th = sk.zero_pose((2,))
    with pytest.raises(ValueError, match="target_positions: expected shape"):
        fit_pose_lm(sk, th, torch.zeros(2, 3, 3), [0, 1])
    with pytest.raises(ValueError, match="theta0"):
        fit_pose_lm(sk, th[:, :5], torch.zeros(2, 1, 3), [0])
    with pytest.raises(ValueError, match="finite"):
        fit_pose_lm(sk, th, torch.full((2, 1, 3), float("nan"), dtype=torch.float64), [0])
    with pytest.raises(KeyError, match="unknown joint"):
        fit_pose_lm(sk, th, torch.zeros(2, 1, 3, dtype=torch.float64), ["nose"])
