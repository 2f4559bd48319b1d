"""Tangent-space Gaussian on SO(3) and the Gaussian-on-parameters baseline."""

from __future__ import annotations

import math

import pytest
import scipy.stats as st
import torch

from torchmocap.distributions import (
    ParameterGaussianNoise,
    TangentGaussianSO3,
    VonMisesFisher,
    add_parameter_noise,
    kappa_to_tangent_std,
)
from torchmocap.geometry import (
    geodesic_angle,
    quaternion_angle,
    quaternion_to_matrix,
    random_quaternion,
)

F64 = torch.float64


class TestTangentGaussianSO3:
    def test_smoke(self):
        d = TangentGaussianSO3(torch.tensor([1.0, 0, 0, 0]), 0.1)
        assert d.sample((3,)).shape == (3, 4)
        d = TangentGaussianSO3(torch.eye(3), 0.1)
        assert d.sample((3,)).shape == (3, 3, 3)

    def test_cardinality(self):
        g = torch.Generator().manual_seed(0)
        q = random_quaternion((2, 5), g)
        d = TangentGaussianSO3(q, torch.full((5,), 0.2))
        x = d.sample((7,), generator=g)
        assert x.shape == (7, 2, 5, 4) and d.log_prob(x).shape == (7, 2, 5)
        dm = TangentGaussianSO3(quaternion_to_matrix(q), 0.2)
        assert dm.sample((7,), generator=g).shape == (7, 2, 5, 3, 3)

    def test_exception(self):
        with pytest.raises(ValueError, match="loc"):
            TangentGaussianSO3(torch.tensor([1.0, 1.0, 0, 0]), 0.1)
        with pytest.raises(ValueError, match="loc"):
            TangentGaussianSO3(torch.zeros(5), 0.1)
        with pytest.raises(ValueError, match="loc"):
            TangentGaussianSO3(2 * torch.eye(3), 0.1)
        with pytest.raises(ValueError, match="scale"):
            TangentGaussianSO3(torch.tensor([1.0, 0, 0, 0]), -0.1)

    def test_feature_angle_distribution(self):
        """angle^2 / sigma^2 ~ chi^2_3 around any mean; matrix and quaternion forms agree."""
        g = torch.Generator().manual_seed(1)
        q0 = random_quaternion((), g, dtype=F64)
        sigma = 0.05
        d = TangentGaussianSO3(q0, sigma)
        x = d.sample((20000,), generator=torch.Generator().manual_seed(2))
        ang = quaternion_angle(q0.expand_as(x), x)
        assert st.kstest((ang / sigma).numpy() ** 2, st.chi2(3).cdf).pvalue > 1e-3
        dm = TangentGaussianSO3(quaternion_to_matrix(q0), sigma)
        xm = dm.sample((20000,), generator=torch.Generator().manual_seed(2))
        assert torch.allclose(quaternion_to_matrix(x), xm, atol=1e-10)
        angm = geodesic_angle(quaternion_to_matrix(q0).expand_as(xm), xm)
        assert torch.allclose(ang, angm, atol=1e-8)

    def test_feature_log_prob(self):
        g = torch.Generator().manual_seed(3)
        q0 = random_quaternion((), g, dtype=F64)
        d = TangentGaussianSO3(q0, 0.3)
        v = d.sample_tangent((50,), generator=g)
        from torchmocap.geometry import axis_angle_to_quaternion, quaternion_multiply

        x = quaternion_multiply(q0, axis_angle_to_quaternion(v))
        ref = torch.distributions.Normal(0.0, 0.3).log_prob(v).sum(-1)
        assert torch.allclose(d.log_prob(x), ref, atol=1e-9)
        assert torch.allclose(d.log_prob(-x), ref, atol=1e-9)  # q and -q are one rotation
        assert d.entropy().item() == pytest.approx(
            torch.distributions.Normal(0.0, 0.3).entropy().item() * 3)

    def test_feature_equivalent_to_vmf_at_large_kappa(self):
        """sigma = 2 / sqrt(kappa): rotation angles indistinguishable from vMF(kappa=1000)."""
        kappa = 1000.0
        e = torch.tensor([1.0, 0, 0, 0], dtype=F64)
        a = VonMisesFisher(e, torch.tensor(kappa, dtype=F64)).sample(
            (8000,), generator=torch.Generator().manual_seed(4))
        b = TangentGaussianSO3(e, kappa_to_tangent_std(kappa)).sample(
            (8000,), generator=torch.Generator().manual_seed(5))
        ang_a = quaternion_angle(e.expand_as(a), a)
        ang_b = quaternion_angle(e.expand_as(b), b)
        assert st.ks_2samp(ang_a.numpy(), ang_b.numpy()).pvalue > 1e-3
        assert math.degrees(ang_b.median().item()) == pytest.approx(5.6, rel=0.03)

    @pytest.mark.parametrize("representation", ["quaternion", "matrix"])
    def test_gradcheck_log_prob(self, representation):
        """log_prob is differentiable in the value, the mean rotation (both moved along the
        group, through tangent vectors) and the scale; float64, tiny case."""
        from torchmocap.geometry import axis_angle_to_quaternion, quaternion_multiply

        g = torch.Generator().manual_seed(6)
        q0 = random_quaternion((2,), g, dtype=F64)
        v = (0.3 * torch.randn(3, 2, 3, generator=g, dtype=F64)).requires_grad_()
        w = (0.1 * torch.randn(2, 3, generator=g, dtype=F64)).requires_grad_()
        s = torch.tensor([0.2, 0.5], dtype=F64, requires_grad=True)

        def conv(q):
            return q if representation == "quaternion" else quaternion_to_matrix(q)

        def lp(v, w, s):
            loc = quaternion_multiply(q0, axis_angle_to_quaternion(w))
            x = quaternion_multiply(q0.expand(3, 2, 4), axis_angle_to_quaternion(v))
            return TangentGaussianSO3(conv(loc), s, validate_args=False).log_prob(conv(x))

        assert torch.autograd.gradcheck(lp, (v, w, s))
        # at loc = q0 (w = 0) the gradient in v is the Gaussian's: -v / s^2
        (gv,) = torch.autograd.grad(lp(v, torch.zeros(2, 3, dtype=F64), s).sum(), v)
        torch.testing.assert_close(gv, -v.detach() / s.detach()[:, None] ** 2)

    def test_rsample_gradient(self):
        q0 = torch.tensor([1.0, 0, 0, 0], dtype=F64)
        s = torch.tensor(0.2, dtype=F64, requires_grad=True)
        x = TangentGaussianSO3(q0, s).rsample((4,), generator=torch.Generator().manual_seed(0))
        x.sum().backward()
        assert s.grad is not None and torch.isfinite(s.grad)


class TestParameterNoise:
    def test_feature(self):
        g = torch.Generator().manual_seed(0)
        theta = torch.zeros(20000, 10, dtype=F64)
        out = add_parameter_noise(theta, [1, 4, 5], 0.06, generator=g)
        assert torch.equal(out[:, [0, 2, 3, 6, 7, 8, 9]], theta[:, [0, 2, 3, 6, 7, 8, 9]])
        assert torch.allclose(out[:, [1, 4, 5]].std(0), torch.full((3,), 0.06, dtype=F64),
                              rtol=0.03)
        assert torch.equal(theta, torch.zeros_like(theta))  # input untouched

    def test_module(self):
        m = ParameterGaussianNoise([0, 2], [0.1, 0.2])
        th = torch.zeros(5, 3)
        a = m(th, generator=torch.Generator().manual_seed(1))
        b = add_parameter_noise(th, [0, 2], torch.tensor([0.1, 0.2]),
                                generator=torch.Generator().manual_seed(1))
        assert torch.equal(a, b)
        d = torch.tensor([[0.1, -0.2]])
        ref = torch.distributions.Normal(0.0, torch.tensor([0.1, 0.2])).log_prob(d).sum(-1)
        assert torch.allclose(m.log_prob(d), ref)

    def test_exception(self):
        with pytest.raises(ValueError, match="indices"):
            add_parameter_noise(torch.zeros(3, 4), [4], 0.1)
        with pytest.raises(ValueError, match="std"):
            add_parameter_noise(torch.zeros(3, 4), [1], -0.1)
