"""ManifoldProposal with each sensor-noise model, and the base pieces of the proposal interface."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.distributions import kappa_to_tangent_std
from torchmocap.geometry import geodesic_angle, matrix_to_quaternion
from torchmocap.ik import SensorManifold
from torchmocap.proposals import (
    GaussianDiffusionProposal,
    ManifoldProposal,
    NoSensorNoise,
    PassiveGaussianNoise,
    ProposalContext,
    TangentGaussianNoise,
    VonMisesFisherNoise,
    select_ancestors,
)
from torchmocap.skeleton import human31

F64 = torch.float64

NOISES = {
    "none": lambda kappa=1000.0: NoSensorNoise(),
    "gaussian": lambda kappa=1000.0: PassiveGaussianNoise(kappa=kappa),
    "vmf": lambda kappa=1000.0: VonMisesFisherNoise(kappa),
    "tangent_gaussian": lambda kappa=1000.0: TangentGaussianNoise(kappa=kappa),
}


@pytest.fixture(scope="module")
def setup():
    sk = human31().double()
    m = SensorManifold(sk).double()
    th = torch.zeros(31, dtype=F64)
    th[sk.joint_dofs("l_elbow")] = 0.6
    th[sk.joint_dofs("r_knee")] = 0.4
    th[sk.joint_dofs("l_shoulder")] = torch.tensor([0.3, 0.2, -0.1], dtype=F64)
    return sk, m, th


class TestBase:
    def test_select_ancestors(self):
        prev = torch.arange(12.0).reshape(4, 3)
        g = torch.Generator().manual_seed(0)
        assert torch.equal(select_ancestors(ProposalContext(prev), 4, 3, g), prev)
        out = select_ancestors(ProposalContext(prev), 10, 3, g)
        assert out.shape == (10, 3)
        lw = torch.tensor([-1e9, 0.0, -1e9, -1e9])
        out = select_ancestors(ProposalContext(prev, log_weights=lw), 6, 3, g)
        assert torch.equal(out, prev[1].expand(6, 3))
        assert select_ancestors(ProposalContext(prev[0]), 5, 3, g).shape == (5, 3)
        with pytest.raises(ValueError, match="previous"):
            select_ancestors(ProposalContext(torch.zeros(4, 2)), 4, 3, g)
        with pytest.raises(ValueError, match="num"):
            select_ancestors(ProposalContext(prev), 0, 3, g)

    def test_gaussian_diffusion(self):
        g = torch.Generator().manual_seed(1)
        p = GaussianDiffusionProposal([0.1, 0.0, 0.3], 3)
        out = p.sample(ProposalContext(torch.zeros(3, dtype=F64)), 20000, g)
        assert torch.allclose(out.particles.std(0), torch.tensor([0.1, 0.0, 0.3], dtype=F64),
                              rtol=0.03)
        ref = (torch.distributions.Normal(0.0, 0.1).log_prob(out.particles[:, 0])
               + torch.distributions.Normal(0.0, 0.3).log_prob(out.particles[:, 2]))
        assert torch.allclose(out.log_q, ref, atol=1e-6)  # std buffer is float32
        pc = GaussianDiffusionProposal(1.0, 3, lower=torch.full((3,), -0.5),
                                       upper=torch.full((3,), 0.5))
        x = pc.sample(ProposalContext(torch.zeros(3)), 1000, g).particles
        assert float(x.abs().max()) <= 0.5 and x.abs().max() == 0.5

    def test_exception(self):
        with pytest.raises(ValueError, match="std"):
            GaussianDiffusionProposal([0.1, 0.2], 3)
        with pytest.raises(ValueError, match="std"):
            GaussianDiffusionProposal(-1.0, 3)
        with pytest.raises(ValueError, match="boundary"):
            GaussianDiffusionProposal(1.0, 3, boundary="wrap")
        with pytest.raises(ValueError, match="rotation_std_deg"):
            GaussianDiffusionProposal.from_skeleton(human31(), rotation_std_deg=float("nan"))
        p = GaussianDiffusionProposal(1.0, 3)
        with pytest.raises(ValueError, match="context.std"):
            p.sample(ProposalContext(torch.zeros(3), std=torch.ones(4)), 5)
        with pytest.raises(ValueError, match="context.scale"):
            p.sample(ProposalContext(torch.zeros(3), scale=-1.0), 5)

    def test_feature_context_std_and_scale(self):
        """An annealer's per-layer std replaces the proposal's own; ``scale`` multiplies it."""
        g = torch.Generator().manual_seed(7)
        p = GaussianDiffusionProposal([0.1, 0.2, 0.3], 3)
        prev = torch.zeros(3, dtype=F64)
        own = p.sample(ProposalContext(prev, scale=0.5), 40000, g).particles.std(0)
        assert torch.allclose(own, torch.tensor([0.05, 0.1, 0.15], dtype=F64), rtol=0.03)
        std = torch.tensor([0.4, 0.0, 0.01], dtype=F64)
        got = p.sample(ProposalContext(prev, std=std, scale=0.5), 40000, g).particles.std(0)
        assert torch.allclose(got, std, rtol=0.03)
        assert torch.equal(p.coordinates(prev), prev) and torch.equal(p.coordinate_std, p.std)

    def test_feature_from_skeleton(self):
        sk = human31()
        p = GaussianDiffusionProposal.from_skeleton(sk, rotation_std_deg=2.0,
                                                    translation_std=0.05, boundary="reflect")
        assert p.std[sk.translation_dofs].tolist() == pytest.approx([0.05] * 3)
        rot = [d for d in range(31) if d not in sk.translation_dofs]
        assert torch.allclose(p.std[rot], torch.full((28,), math.radians(2.0)))
        x = p.sample(ProposalContext(sk.upper.clone().clamp(max=10)), 500,
                     torch.Generator().manual_seed(0)).particles
        assert bool(sk.within_limits(x).all())  # reflected into the limits


class TestManifoldProposal:
    @pytest.mark.parametrize("noise", list(NOISES))
    def test_smoke(self, setup, noise):
        sk, m, th = setup
        prop = ManifoldProposal(m, active_std=0.05, noise=NOISES[noise](),
                                compute_residual=True)
        assert not ManifoldProposal(m, noise=NOISES[noise]()).compute_residual  # orthogonal
        ctx = ProposalContext(previous=th, sensors=m.sensor_orientations(th))
        out = prop.sample(ctx, 50, torch.Generator().manual_seed(0))
        assert out.particles.shape == (50, 31) and out.particles.dtype == F64
        assert torch.isfinite(out.particles).all()
        assert out.stats["residual_max_deg"] < 1e-6
        assert out.log_q is None

    def test_feature_none_matches_sensors_exactly(self, setup):
        sk, m, th = setup
        prop = ManifoldProposal(m, active_std=0.1, noise=NoSensorNoise())
        S = m.sensor_orientations(th)
        out = prop.sample(ProposalContext(previous=th, sensors=S), 2000,
                          torch.Generator().manual_seed(1))
        got = m.bone_orientations(out.particles)
        assert float(geodesic_angle(got, m.bone_orientations(th).expand_as(got)).max()) < 1e-9
        # active coordinates are diffused with the requested std (clamped ones excluded)
        d = m(out.particles) - m(th)
        free = [i for i, n in enumerate(m.active_names) if "elbow" not in n and "knee" not in n
                and "ankle" not in n]
        assert torch.allclose(d[:, free].std(0), torch.full((len(free),), 0.1, dtype=F64),
                              rtol=0.06)
        # quaternion sensors give the same particles
        out_q = prop.sample(ProposalContext(previous=th, sensors=matrix_to_quaternion(S)), 2000,
                            torch.Generator().manual_seed(1))
        assert torch.allclose(out_q.particles, out.particles, atol=1e-10)

    @pytest.mark.parametrize("noise", ["vmf", "tangent_gaussian"])
    def test_feature_rotation_noise_angles(self, setup, noise):
        """Bone orientation error = angle of the sensor noise: median 176/sqrt(kappa) deg."""
        sk, m, th = setup
        kappa = 400.0
        prop = ManifoldProposal(m, active_std=0.0, noise=NOISES[noise](kappa))
        S = m.sensor_orientations(th)
        out = prop.sample(ProposalContext(previous=th, sensors=S), 4000,
                          torch.Generator().manual_seed(2))
        ang = geodesic_angle(m.bone_orientations(out.particles),
                             m.bone_orientations(th).expand(4000, 5, 3, 3))
        med = math.degrees(float(ang.median()))
        assert med == pytest.approx(176.0 / math.sqrt(kappa), rel=0.05)

    def test_feature_gaussian_on_passive_parameters(self, setup):
        sk, m, th = setup
        prop = ManifoldProposal(m, active_std=0.0, noise=PassiveGaussianNoise(kappa=1000.0))
        out = prop.sample(ProposalContext(previous=th, sensors=m.sensor_orientations(th)),
                          8000, torch.Generator().manual_seed(3))
        d = out.particles - th
        pidx = m.passive_index.flatten()
        sd = d[:, pidx].std(0)
        assert torch.allclose(sd, torch.full_like(sd, kappa_to_tangent_std(1000.0)), rtol=0.05)
        assert float(d[:, m.active_index].abs().max()) < 1e-9

    def test_feature_per_particle_previous_and_decode(self, setup):
        sk, m, th = setup
        g = torch.Generator().manual_seed(4)
        prev = th + 0.05 * torch.randn(30, 31, generator=g, dtype=F64)
        prop = ManifoldProposal(m, active_std=0.0, noise=NoSensorNoise())
        S = m.sensor_orientations(th)
        out = prop.sample(ProposalContext(previous=prev, sensors=S), 30, g)
        assert torch.allclose(m(out.particles), torch.clamp(m(prev), prop.active_lower.double(),
                                                             prop.active_upper.double()))
        sol = prop.decode(m(out.particles), S, g, reference=out.particles)
        assert torch.allclose(sol.theta, out.particles, atol=1e-9)

    def test_exception(self, setup):
        sk, m, th = setup
        with pytest.raises(TypeError, match="noise"):
            ManifoldProposal(m, noise="cauchy")
        with pytest.raises(ValueError, match="kappa"):
            VonMisesFisherNoise(kappa=0.0)
        with pytest.raises(ValueError, match="std_deg"):
            TangentGaussianNoise(std_deg=-1.0)
        with pytest.raises(ValueError, match="active_std"):
            ManifoldProposal(m, active_std=[0.1, 0.2])
        with pytest.raises(ValueError, match="sensors"):
            ManifoldProposal(m).sample(ProposalContext(previous=th), 10)
        bad = torch.zeros(5, 4, dtype=F64)
        with pytest.raises(ValueError, match="sensors"):
            ManifoldProposal(m).sample(ProposalContext(previous=th, sensors=bad), 10)
        # the check runs once per sensors tensor (every layer of a frame passes the same one),
        # but a tensor changed in place, or a new one, is checked again
        prop = ManifoldProposal(m)
        S = m.sensor_orientations(th).clone()
        prop.sample(ProposalContext(previous=th, sensors=S), 10)
        S.mul_(2.0)  # no longer rotations
        with pytest.raises(ValueError, match="sensors"):
            prop.sample(ProposalContext(previous=th, sensors=S), 10)
        with pytest.raises(ValueError, match="sensors"):
            prop.sample(ProposalContext(previous=th, sensors=2 * m.sensor_orientations(th)), 10)

    def test_module(self, setup):
        sk, m, th = setup
        prop = ManifoldProposal(m, active_std=0.05, noise=VonMisesFisherNoise())
        ctx = ProposalContext(previous=th, sensors=m.sensor_orientations(th))
        a = prop(ctx, 20, torch.Generator().manual_seed(5)).particles
        b = prop.sample(ctx, 20, torch.Generator().manual_seed(5)).particles
        assert torch.equal(a, b)  # same seed, same particles

    def test_feature_coordinates_and_layer_std(self, setup):
        """The proposal's coordinates are the active ones; a per-layer std applies there."""
        sk, m, th = setup
        prop = ManifoldProposal(m, rotation_std_deg=3.0, translation_std=0.02,
                                noise=NoSensorNoise(), clamp_active=False)
        assert torch.equal(prop.coordinates(th), m(th))
        trans = [i for i, d in enumerate(m.active_dofs) if d in sk.translation_dofs]
        assert prop.coordinate_std[trans].tolist() == pytest.approx([0.02] * len(trans))
        std = torch.full((m.num_active,), 0.01, dtype=F64)
        out = prop.sample(ProposalContext(previous=th, sensors=m.sensor_orientations(th),
                                          std=std), 20000, torch.Generator().manual_seed(8))
        assert torch.allclose((m(out.particles) - m(th)).std(0), std, rtol=0.04)


class TestSensorNoise:
    def test_feature_sensor_rotations_angles(self):
        """vMF and tangent noise at kappa = 1000 have the median angle 176/sqrt(kappa) deg."""
        R = torch.eye(3, dtype=F64).expand(2, 3, 3)
        for noise in (VonMisesFisherNoise(1000.0), TangentGaussianNoise(kappa=1000.0)):
            Rn = noise.sensor_rotations(R, 5000, torch.Generator().manual_seed(0))
            med = math.degrees(float(geodesic_angle(Rn, R.expand_as(Rn)).median()))
            assert med == pytest.approx(176.0 / math.sqrt(1000.0), rel=0.05)
        assert torch.equal(NoSensorNoise().sensor_rotations(R, 3), R.expand(3, 2, 3, 3))
        assert torch.equal(PassiveGaussianNoise().sensor_rotations(R, 3), R.expand(3, 2, 3, 3))

    def test_feature_passive_std(self):
        th = torch.zeros(20000, 6, dtype=F64)
        out = PassiveGaussianNoise(std_deg=2.0).perturb_passive(
            th, torch.tensor([[1, 3, 5]]), torch.Generator().manual_seed(1))
        assert float(out[:, [0, 2, 4]].abs().max()) == 0
        assert torch.allclose(out[:, [1, 3, 5]].std(0), torch.full((3,), math.radians(2.0),
                                                                    dtype=F64), rtol=0.03)


class TestDroppedSamples:
    def test_feature_dropped_sensor_follows_the_ancestor(self, setup):
        """A dropped (held, stale) sample carries no information: its passive joint follows
        the particle's ancestor instead of snapping to the stale orientation; the valid sensors
        are still met exactly."""
        sk, m, th = setup
        stale = th.clone()
        stale[sk.joint_dofs("l_shoulder")] += torch.tensor([0.6, -0.4, 0.5], dtype=F64)
        S = m.sensor_orientations(stale)  # every sensor reads the stale pose ...
        S[[0, 2, 3, 4]] = m.sensor_orientations(th)[[0, 2, 3, 4]]  # ... but l_forearm
        valid = torch.tensor([True, False, True, True, True])
        prop = ManifoldProposal(m, active_std=0.0, noise=NoSensorNoise(),
                                dropped_spread_deg=2.0)
        out = prop.sample(ProposalContext(previous=th, sensors=S, sensor_valid=valid), 400,
                          torch.Generator().manual_seed(9))
        got = m.bone_orientations(out.particles)
        want = m.bone_orientations(th).expand_as(got)
        err = geodesic_angle(got, want)
        assert float(err[:, [0, 2, 3, 4]].max()) < 1e-9
        med = math.degrees(float(err[:, 1].median()))
        assert 1.0 < med < 5.0  # spread around the ancestor (2 deg per axis), not ~40 deg
        assert out.stats["dropped_sensors"] == 1
        # without the flag the stale value is obeyed
        out2 = prop.sample(ProposalContext(previous=th, sensors=S), 50,
                           torch.Generator().manual_seed(9))
        stale_err = geodesic_angle(m.bone_orientations(out2.particles)[:, 1],
                                   m.bone_orientations(stale)[1].expand(50, 3, 3))
        assert float(stale_err.max()) < 1e-9

    def test_feature_limit_resampling(self, setup):
        sk, m, th = setup
        g = torch.Generator().manual_seed(3)
        keep = ManifoldProposal(m, rotation_std_deg=25.0, noise=VonMisesFisherNoise(50.0))
        res = ManifoldProposal(m, rotation_std_deg=25.0, noise=VonMisesFisherNoise(50.0),
                               limits="resample", limit_tries=6)
        ctx = ProposalContext(previous=th, sensors=m.sensor_orientations(th))
        a = keep.sample(ctx, 2000, g)
        b = res.sample(ctx, 2000, g)
        assert a.stats["within_limits"] < 0.99  # the wide draw leaves the limits ...
        assert b.stats["within_limits"] > a.stats["within_limits"]  # ... redraws fix most
        assert b.stats["resampled"] > 0
        with pytest.raises(ValueError, match="limits"):
            ManifoldProposal(m, limits="clamp")
