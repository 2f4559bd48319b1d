"""Synthetic IMUs: exact noise-free orientations, device-noise spread, misalignment, desync,
drift, drops, placement errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats as st
import torch

from torchmocap.data.imu import SensorPlacementError
from torchmocap.data.synthetic.imu import synthesize_imu
from torchmocap.data.synthetic.scenario import SENSOR_BONES, TRACKING_SENSORS
from torchmocap.geometry import (
    matrix_to_quaternion,
    quaternion_angle,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_slerp,
    quaternion_to_matrix,
    random_rotation_matrix,
)
from torchmocap.skeleton import human31

NAMES = human31().joint_names


def _bones(T: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    return random_rotation_matrix((T, len(NAMES)), torch.Generator().manual_seed(seed),
                                  dtype=dtype)


def _imu(R, **kw):
    args = dict(fps=25.0, generator=torch.Generator().manual_seed(1), noise="none")
    args.update(kw)
    return synthesize_imu(R, NAMES, dict(SENSOR_BONES), list(TRACKING_SENSORS), **args)


def _deg(x: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(x)


def _vmf_angle_cdf(kappa: float):
    """CDF of the rotation angle of vMF(S^3, kappa) quaternion noise around the identity.

    With ``w = cos(angle / 2)`` the density of ``w`` is ``∝ e^{kappa w} sqrt(1 - w^2)``; in
    ``s = kappa (1 - w) = 2 kappa sin^2(angle / 4)`` it is ``∝ e^{-s} sqrt(s (2 - s / kappa))``
    (integrated numerically; ``w < 0`` has probability ``e^{-2 kappa}``, nil here).
    """
    s = np.linspace(0.0, min(2 * kappa, 80.0), 200001)
    f = np.exp(-s) * np.sqrt(np.clip(s * (2 - s / kappa), 0, None))
    c = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(s))])
    c /= c[-1]
    return lambda angle: np.interp(2 * kappa * np.sin(np.asarray(angle) / 4) ** 2, s, c)


class TestImu:
    def test_smoke(self):
        d = _imu(_bones(5))
        assert d.quaternions.shape == (5, 10, 4) and d.clean.shape == (5, 10, 4)
        assert d.valid.shape == (5, 10) and bool(d.valid.all())
        assert d.offsets.shape == (10, 4) and d.names == list(SENSOR_BONES)
        assert d.tracking.tolist() == [n in TRACKING_SENSORS for n in SENSOR_BONES]
        assert d.select("tracking").names == list(TRACKING_SENSORS)
        assert d.select("validation").names == ["chest", "l_upper_arm", "r_upper_arm",
                                                "l_thigh", "r_thigh"]

    def test_noise_free_is_ground_truth_times_offset(self, dtype):
        R = _bones(7, dtype=dtype)
        d = _imu(R)
        idx = [NAMES.index(b) for b in SENSOR_BONES.values()]
        expect = R[:, idx] @ quaternion_to_matrix(d.offsets)[None]
        tol = 1e-5 if dtype == torch.float32 else 1e-12
        assert torch.allclose(quaternion_to_matrix(d.clean), expect, atol=tol)
        # with every error switched off the measurement is the clean orientation
        assert torch.allclose(quaternion_to_matrix(d.quaternions), expect, atol=tol)
        # offsets are proper, distinct, seeded random rotations; identity on request
        assert float(_deg(quaternion_angle(d.offsets[0], d.offsets[1]))) > 1
        assert torch.equal(_imu(R).offsets, d.offsets)
        ident = _imu(R, offset="identity")
        assert torch.allclose(quaternion_to_matrix(ident.clean), R[:, idx], atol=tol)

    @pytest.mark.parametrize("kappa", [100.0, 1000.0])
    def test_vmf_spread(self, kappa):
        """Noise angles follow the model's law (KS test against the exact vMF(S^3) angle
        distribution), and the same test rejects a 15 % wrong concentration (power)."""
        d = _imu(_bones(400), noise="vmf", kappa=kappa)
        ang = quaternion_angle(d.clean, d.quaternions).flatten()  # 4000 samples (radians)
        assert st.kstest(ang.numpy(), _vmf_angle_cdf(kappa)).pvalue > 1e-3
        assert st.kstest(ang.numpy(), _vmf_angle_cdf(0.85 * kappa)).pvalue < 1e-3
        assert st.kstest(ang.numpy(), _vmf_angle_cdf(1.15 * kappa)).pvalue < 1e-3

    def test_tangent_spread(self):
        """|N(0, sigma^2 I_3)| is Maxwell-distributed: KS test, with power against 10 % off."""
        d = _imu(_bones(400), noise="tangent", tangent_std_deg=2.0)
        ang = quaternion_angle(d.clean, d.quaternions).flatten().numpy()
        sigma = math.radians(2.0)
        assert st.kstest(ang, st.maxwell(scale=sigma).cdf).pvalue > 1e-3
        assert st.kstest(ang, st.maxwell(scale=0.9 * sigma).cdf).pvalue < 1e-3
        assert st.kstest(ang, st.maxwell(scale=1.1 * sigma).cdf).pvalue < 1e-3

    def test_student_t_spread(self):
        """The angle of t-distributed tangent noise is sigma * |t_3(dof)|-norm: its law is the
        Maxwell law of a Gaussian rescaled by sqrt(dof / chi2_dof) — a KS test against that
        law (sampled independently with scipy), and heavier tails than the Gaussian of the same
        scale (power against the tangent model)."""
        sigma, dof = 2.0, 3.0
        d = _imu(_bones(400), noise="student_t", tangent_std_deg=sigma, dof=dof)
        ang = quaternion_angle(d.clean, d.quaternions).flatten().numpy()
        rng = np.random.default_rng(0)
        ref = (math.radians(sigma) * np.linalg.norm(rng.standard_normal((200000, 3)), axis=1)
               * np.sqrt(dof / rng.chisquare(dof, 200000)))
        ref = np.minimum(ref, math.pi)
        assert st.ks_2samp(ang, ref).pvalue > 1e-3
        assert st.kstest(ang, st.maxwell(scale=math.radians(sigma)).cdf).pvalue < 1e-6
        # heavy tails: far more draws beyond 4 sigma than the Gaussian's ~0.1 %
        assert float(np.mean(ang > 4 * math.radians(sigma))) > 0.03

    def test_heading_walk_variance_grows_linearly(self):
        """Magnetic disturbance: per sensor a random walk of the heading about world z, with
        variance heading_walk_deg^2 per second."""
        T, fps, walk = 126, 25.0, 3.0  # 5 s
        angles = []
        for s in range(40):
            d = _imu(_bones(T), fps=fps, heading_walk_deg=walk,
                     generator=torch.Generator().manual_seed(s))
            err = quaternion_multiply(d.quaternions, quaternion_conjugate(d.clean))
            axis = torch.nn.functional.normalize(err[1:, :, 1:], dim=-1)
            assert bool((axis[..., 2].abs() > 1 - 1e-6).all())  # about world z
            err = err * torch.where(err[..., :1] < 0, -1.0, 1.0)  # q and -q: the same rotation
            angles.append(2 * torch.atan2(err[..., 3], err[..., 0]))  # signed, (T, S)
        a = torch.rad2deg(torch.stack(angles))  # (40, T, S)
        assert float(a[:, 0].abs().max()) < 1e-9
        var_5s = float(a[:, -1].var())  # 400 walks: var ~ walk^2 * 5 s = 45 deg^2
        assert 0.8 * walk**2 * 5 < var_5s < 1.2 * walk**2 * 5
        var_1s = float(a[:, int(fps)].var())
        assert 0.75 * walk**2 < var_1s < 1.25 * walk**2

    def test_misalignment_exact_angle_on_the_left(self):
        R = _bones(6)
        d = _imu(R, misalignment_deg=7.0)
        assert abs(float(_deg(quaternion_angle(d.misalignment, torch.tensor(
            [1.0, 0, 0, 0], dtype=torch.float64)))) - 7.0) < 1e-9
        # q = q_mis ⊗ q_clean for every sensor and frame
        q = quaternion_multiply(d.misalignment.expand_as(d.clean), d.clean)
        assert float(quaternion_angle(q, d.quaternions).max()) < 1e-7
        ang = _deg(quaternion_angle(d.clean, d.quaternions))
        assert float(ang.max()) <= 7.0 + 1e-6
        # a range is sampled uniformly within bounds
        for s in range(5):
            e = _imu(R, misalignment_deg=[5.0, 10.0], generator=torch.Generator().manual_seed(s))
            a = float(_deg(quaternion_angle(e.misalignment, torch.tensor(
                [1.0, 0, 0, 0], dtype=torch.float64))))
            assert 5.0 - 1e-9 <= a <= 10.0 + 1e-9

    def test_heading_drift(self):
        T, fps = 251, 25.0  # 10 s
        d = _imu(_bones(T), fps=fps, drift_deg_per_min=30.0)
        err = quaternion_multiply(d.quaternions, quaternion_conjugate(d.clean))  # left error
        ang = _deg(quaternion_angle(d.clean, d.quaternions))
        expect = 30.0 * torch.arange(T, dtype=torch.float64) / fps / 60.0
        assert torch.allclose(ang, expect[:, None].expand(T, 10), atol=1e-6)
        # about world z
        axis = torch.nn.functional.normalize(err[1:, :, 1:], dim=-1)
        assert bool((axis[..., 2].abs() > 1 - 1e-6).all())
        assert set(torch.sign(d.drift_rates).tolist()) <= {-1.0, 1.0}

    def test_desync_slerps_neighbouring_frames(self):
        R = _bones(8)
        d = _imu(R, desync_frames=0.25)
        q_tb = matrix_to_quaternion(R[:, [NAMES.index(b) for b in SENSOR_BONES.values()]])
        expect = quaternion_slerp(q_tb[:-1], q_tb[1:], 0.25)
        expect = quaternion_multiply(expect, d.offsets[None])
        assert float(quaternion_angle(expect, d.quaternions[:-1]).max()) < 1e-7
        # the last frame is clamped to the clip
        assert float(quaternion_angle(d.clean[-1], d.quaternions[-1]).max()) < 1e-7

    def test_dropped_samples_hold_last_value(self):
        d = _imu(_bones(200), noise="vmf", kappa=1000.0, drop_prob=0.2)
        v = d.valid
        assert bool(v[0].all()) and 0.15 < float((~v).float().mean()) < 0.25
        assert bool(torch.isfinite(d.quaternions).all())
        T = v.shape[0]
        for s in range(10):
            last = 0
            for t in range(T):
                if bool(v[t, s]):
                    last = t
                else:
                    assert torch.equal(d.quaternions[t, s], d.quaternions[last, s])

    def test_exception(self):
        R = _bones(3)
        with pytest.raises(SensorPlacementError, match="tail"):
            synthesize_imu(R, NAMES, {"tailbone": "tail"}, [], 25.0, torch.Generator())
        with pytest.raises(SensorPlacementError, match="tracking"):
            synthesize_imu(R, NAMES, {"back": "pelvis"}, ["chest"], 25.0, torch.Generator())
        with pytest.raises(ValueError, match="bone_rotations"):
            synthesize_imu(R[0], NAMES, {"back": "pelvis"}, [], 25.0, torch.Generator())
        with pytest.raises(ValueError, match="at least one frame"):
            synthesize_imu(R[:0], NAMES, {"back": "pelvis"}, [], 25.0, torch.Generator())
        with pytest.raises(ValueError, match="noise"):
            _imu(R, noise="laplace")
        with pytest.raises(ValueError, match="which"):
            _imu(R).select("all")


@pytest.mark.parametrize("ground_truth", ["source", "fitted"])
def test_ground_truth_source_vs_fitted(ground_truth):
    """``fitted`` makes IMUs, ground truth and images come from one human31 pose: the sensor
    manifold's g^-1 at the true active coordinates then returns the true passive joints."""
    from torchmocap.data.subjects.mocap import fit_subject
    from torchmocap.data.synthetic import load_scenario, synthesize
    from torchmocap.geometry import geodesic_angle
    from torchmocap.ik.sensor_manifold import SensorManifold
    from torchmocap.io import bundled_clip_path, load_motion

    clip = load_motion(bundled_clip_path()).resample(25).slice(0, 12)
    subject = fit_subject(clip)
    sc = load_scenario("clean", ground_truth=ground_truth,
                       **{"silhouettes.enabled": False, "images.enabled": False,
                          "depth.enabled": False, "joints2d.enabled": False})
    seq = synthesize(subject, sc, seed=0)
    gt = seq.ground_truth
    sk = gt.build_skeleton().double()
    fk = sk(gt.theta.double())
    gap = geodesic_angle(fk.rotations, gt.rotations.double()).max()
    sensors = {n: b for n, b, t in zip(seq.imu.names, seq.imu.bones,
                                       seq.imu.tracking.tolist()) if t}
    tk = seq.imu.tracking.nonzero()[:, 0]
    m = SensorManifold(sk, sensors)
    m.calibrate(gt.theta[0].double(), quaternion_to_matrix(seq.imu.quaternions[0, tk].double()))
    t = 11
    th = gt.theta[t].double()
    inv = m.inverse(th[m.active_index][None], quaternion_to_matrix(
        seq.imu.quaternions[t, tk].double()), reference=th).theta[0]
    err = (inv - th).abs().max()
    if ground_truth == "fitted":
        assert gap < 1e-9  # ground truth = FK of the fitted angles
        assert err < 1e-5
    else:
        assert gap > math.radians(0.5)  # the exact source orientations differ from the fit
        assert torch.allclose(gt.rotations, subject.rotations.to(gt.rotations.dtype))


def test_ground_truth_option_checked():
    from torchmocap.data.synthetic import load_scenario
    from torchmocap.data.synthetic.scenario import ScenarioError

    with pytest.raises(ScenarioError, match="ground_truth"):
        load_scenario("clean", ground_truth="exact")
