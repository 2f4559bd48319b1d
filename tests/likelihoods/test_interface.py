"""The likelihood interface: energy convention, shared forward kinematics, weighted sums,
required modalities, per-frame preparation, bound energies, learnable weights."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.data import Frame
from torchmocap.likelihoods import FrameEnergy, Likelihood, Poses, WeightedSum, check_energy
from torchmocap.skeleton import human31


class CountingSkeleton(torch.nn.Module):
    """A skeleton wrapper counting forward-kinematics calls."""

    def __init__(self, sk):
        super().__init__()
        self.sk = sk
        self.calls = 0

    def forward(self, theta, check_finite=True):
        self.calls += 1
        return self.sk(theta, check_finite=check_finite)

    def __getattr__(self, name):
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self.sk, name)


class ElbowTerm(Likelihood):
    """(left elbow flexion - target)^2, read from the shared kinematics' joint positions."""

    requires = ("joints2d",)

    def __init__(self, target: float = 0.0):
        super().__init__()
        self.target = target
        self.prepared = 0

    def prepare(self, frame):
        self.prepared += 1
        return {"frame": frame.index}

    def energy(self, poses, observation):
        kin = poses.kinematics
        sk = poses.skeleton
        return (poses.theta[:, sk.dof_index("l_elbow_flex")] - self.target) ** 2 + 0 * \
            kin.positions.sum((-1, -2))


class EndpointTerm(Likelihood):
    """Mean z of the capsule endpoints of a body (exercises Poses.endpoints)."""

    requires = ("silhouettes",)

    def __init__(self, body):
        super().__init__()
        self.body = body

    def energy(self, poses, observation):
        return poses.endpoints(self.body)[..., 2].mean((-1, -2))


@pytest.fixture(scope="module")
def sk():
    return human31()


def test_weighted_sum_is_the_weighted_sum_of_its_terms(sk):
    body = CapsuleBody(sk)
    a, b = ElbowTerm(0.3), EndpointTerm(body)
    lik = WeightedSum({"a": a, "b": b}, {"a": 2.0, "b": 0.5})
    th = sk.zero_pose((4,))
    th[:, sk.dof_index("l_elbow_flex")] = torch.tensor([0.0, 0.3, 1.0, 1.5])
    obs = lik.prepare(Frame(index=7, time=0.0))
    assert obs == {"a": {"frame": 7}, "b": Frame(index=7, time=0.0)}
    v = lik.energy(Poses(th, sk), obs)
    ref = 2.0 * a.energy(Poses(th, sk), obs["a"]) + 0.5 * b.energy(Poses(th, sk), obs["b"])
    assert torch.allclose(v, ref)
    assert lik.requires == ("joints2d", "silhouettes")
    assert lik.weights == {"a": 2.0, "b": 0.5}
    terms = lik.term_energies(Poses(th, sk), obs)
    elbow = th[:, sk.dof_index("l_elbow_flex")]
    assert set(terms) == {"a", "b"} and torch.allclose(terms["a"], (elbow - 0.3) ** 2)


def test_zero_weight_terms_are_neither_evaluated_nor_required(sk):
    class Exploding(Likelihood):
        requires = ("depth",)

        def prepare(self, frame):
            raise AssertionError("prepared a switched-off term")

        def energy(self, poses, observation):
            raise AssertionError("evaluated a switched-off term")

    lik = WeightedSum({"a": ElbowTerm(), "x": Exploding()}, {"x": 0.0})
    assert lik.requires == ("joints2d",) and lik.active_terms() == ["a"]
    obs = lik.prepare(Frame(index=0, time=0.0))
    assert lik.energy(Poses(sk.zero_pose((2,)), sk), obs).shape == (2,)


def test_optional_terms_score_only_frames_that_have_what_they_read(sk):
    """An optional term's modalities are not required; a frame without them is scored by the
    other terms (and reports no missing evidence), a frame with them by all."""
    body = CapsuleBody(sk)
    a, b = ElbowTerm(0.3), EndpointTerm(body)
    lik = WeightedSum({"a": a, "b": b}, {"a": 2.0, "b": 0.5}, optional=["b"])
    assert lik.requires == ("joints2d",) and lik.active_terms() == ["a", "b"]
    th = sk.zero_pose((3,))
    bare = lik.prepare(Frame(index=0, time=0.0))
    assert list(bare) == ["a"] and lik.present_terms(bare) == ["a"]
    v = lik.energy(Poses(th, sk), bare)
    assert torch.allclose(v, 2.0 * a.energy(Poses(th, sk), bare["a"]))
    assert lik.evidence(bare) and lik.missing_evidence(bare) == []
    masks = torch.zeros(4, 8, 8, dtype=torch.bool)
    full = lik.prepare(Frame(index=0, time=0.0, silhouettes=masks))
    assert list(full) == ["a", "b"]
    assert torch.allclose(lik.energy(Poses(th, sk), full),
                          v + 0.5 * b.energy(Poses(th, sk), full["b"]))
    assert "optional=['b']" in repr(lik)
    with pytest.raises(ValueError, match=r"optional: no term named \['c'\]"):
        WeightedSum({"a": ElbowTerm()}, optional=["c"])
    with pytest.raises(ValueError, match="optional: expected a list"):
        WeightedSum({"a": ElbowTerm()}, optional="a")


def test_forward_kinematics_runs_once_per_evaluation(sk):
    counting = CountingSkeleton(sk)
    body = CapsuleBody(sk)
    lik = WeightedSum({"a": ElbowTerm(), "b": EndpointTerm(body), "c": ElbowTerm(1.0)})
    V = FrameEnergy(lik, lik.prepare(Frame(index=0, time=0.0)), counting)
    V(sk.zero_pose((5,)))
    # body.skeleton is the real skeleton (not the counter): endpoints then run their own FK,
    # the two elbow terms share one
    assert counting.calls == 1
    body2 = CapsuleBody(sk)
    body2.skeleton = counting
    lik2 = WeightedSum({"a": ElbowTerm(), "b": EndpointTerm(body2)})
    counting.calls = 0
    FrameEnergy(lik2, lik2.prepare(Frame(index=0, time=0.0)), counting)(sk.zero_pose((5,)))
    assert counting.calls == 1  # endpoints reuse the shared kinematics


def test_frame_energy_checks_what_terms_return(sk):
    class Bad(Likelihood):
        def __init__(self, out):
            super().__init__()
            self.out = out

        def energy(self, poses, observation):
            return self.out

    th = sk.zero_pose((3,))
    with pytest.raises(ValueError, match=r"expected an energy of shape \(3,\)"):
        FrameEnergy(Bad(torch.zeros(4)), None, sk)(th)
    with pytest.raises(ValueError, match="NaN"):
        FrameEnergy(Bad(torch.tensor([0.0, float("nan"), 1.0])), None, sk)(th)
    with pytest.raises(ValueError, match=r"terms.b: expected an energy"):
        lik = WeightedSum({"a": ElbowTerm(), "b": Bad(3.0)})
        FrameEnergy(lik, lik.prepare(Frame(index=0, time=0.0)), sk)(th)
    with pytest.raises(ValueError, match="theta"):
        FrameEnergy(ElbowTerm(), None, sk)(th[0])
    with pytest.raises(NotImplementedError):
        Likelihood().energy(Poses(th, sk), None)
    assert check_energy(torch.zeros(2), 2, "x").shape == (2,)


def test_weighted_sum_errors():
    with pytest.raises(ValueError, match="terms"):
        WeightedSum({})
    with pytest.raises(TypeError, match="terms.a"):
        WeightedSum({"a": lambda p, o: 0})
    with pytest.raises(ValueError, match="weights: no term named"):
        WeightedSum({"a": ElbowTerm()}, {"b": 1.0})
    for bad in (-1.0, float("nan"), float("inf"), "2"):
        with pytest.raises(ValueError, match="weights.a"):
            WeightedSum({"a": ElbowTerm()}, {"a": bad})


def test_log_likelihood_is_minus_energy(sk):
    t = ElbowTerm(0.2)
    p = Poses(sk.zero_pose((2,)), sk)
    assert torch.equal(t.log_likelihood(p, None), -t.energy(p, None))


def test_blockwise_splits_rows_into_near_equal_blocks():
    from torchmocap.likelihoods.base import blockwise, check_block

    seen = []

    def rows(x, scale):
        seen.append(x.shape[0])
        return scale * x.sum(-1)

    x = torch.arange(30.0).reshape(10, 3)
    for block in (None, 10, 64):
        seen.clear()
        assert torch.equal(blockwise(rows, x, block, 2.0), 2 * x.sum(-1)) and seen == [10]
    for block, sizes in ((4, [4, 3, 3]), (3, [3, 3, 2, 2]), (1, [1] * 10)):
        seen.clear()
        assert torch.equal(blockwise(rows, x, block, 1.0), x.sum(-1))
        assert seen == sizes and max(sizes) <= block
    for bad in (0, -1, 2.5, True, "8"):
        with pytest.raises(ValueError, match="block: expected an int >= 1"):
            check_block(bad)
    assert check_block(None) is None and check_block(7) == 7


def test_silhouette_blocks_give_the_same_energies():
    from torchmocap.cameras import make_ring_rig
    from torchmocap.likelihoods.silhouette import (
        SilhouetteLikelihood,
        render_capsule_silhouettes,
    )

    sk = human31()
    body = CapsuleBody(sk)
    rig = make_ring_rig(3, image_size=(160, 120)).float()
    masks = render_capsule_silhouettes(body, rig, sk.zero_pose())
    th = sk.zero_pose() + 0.1 * torch.randn(50, sk.num_dofs,
                                            generator=torch.Generator().manual_seed(0))
    frame = Frame(index=0, time=0.0, silhouettes=masks)
    one = SilhouetteLikelihood(body, rig, block=None)
    obs = one.prepare(frame)
    ref = one.energy(Poses(th, sk), obs)
    assert float(ref.std()) > 0.01
    for block in (7, 16, 50):
        got = SilhouetteLikelihood(body, rig, block=block).energy(Poses(th, sk), obs)
        torch.testing.assert_close(got, ref, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="block"):
        SilhouetteLikelihood(body, rig, block=0)
