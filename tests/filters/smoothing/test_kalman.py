"""The constant-velocity Kalman smoother: exact against batch least squares and the explicit
Gaussian likelihood, noise recovered by ML, real motion de-noised, wrapping, limits, wiring."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.assembly import Runtime, build_tracker, tracker_config
from torchmocap.data.synthetic.clips import synthesized_sequence
from torchmocap.filters import FrameInfo, KalmanSmoother, Track
from torchmocap.filters.smoothing import cv_kalman_smoother, fit_cv_noise, unwrap_angles

F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=torch.float64)


def _q_matrix(q):
    return q * torch.tensor([[1 / 3, 1 / 2], [1 / 2, 1.0]], dtype=torch.float64)


def _simulate(T, N, r, q, g):
    """``(y (T, N), x (T, N))``: constant-velocity trajectories with white-noise acceleration,
    observed with noise of variance ``r`` (frame 0 exact)."""
    L = torch.linalg.cholesky(_q_matrix(q))
    s = torch.zeros(N, 2, dtype=torch.float64)
    s[:, 1] = 0.02 * torch.randn(N, generator=g, dtype=torch.float64)
    xs = [s[:, 0].clone()]
    for _ in range(1, T):
        s = s @ F.T + torch.randn(N, 2, generator=g, dtype=torch.float64) @ L.T
        xs.append(s[:, 0].clone())
    x = torch.stack(xs)
    y = x + math.sqrt(r) * torch.randn(T, N, generator=g, dtype=torch.float64)
    y[0] = x[0]
    return y, x


def _batch_least_squares(y, r, q):
    """The smoother's mean, independently: minimise the quadratic trajectory energy over
    ``(v_0, x_1, v_1, ..., x_{T-1}, v_{T-1})`` with ``x_0 = y_0`` (dense normal equations)."""
    T = y.shape[0]
    n = 2 * T
    Qi = torch.linalg.inv(_q_matrix(q))
    A = torch.zeros(n, n, dtype=torch.float64)
    b = torch.zeros(n, dtype=torch.float64)
    for t in range(1, T):  # process terms: (s_t - F s_{t-1})^T Q^-1 (s_t - F s_{t-1})
        M = torch.zeros(2, n, dtype=torch.float64)
        M[:, 2 * t:2 * t + 2] = torch.eye(2, dtype=torch.float64)
        M[:, 2 * t - 2:2 * t] = -F
        A += M.T @ Qi @ M
    for t in range(1, T):  # observation terms
        A[2 * t, 2 * t] += 1 / r
        b[2 * t] += y[t] / r
    free = [i for i in range(n) if i != 0]  # x_0 fixed at y_0
    b_free = b[free] - A[free, 0] * y[0]
    sol = torch.linalg.solve(A[free][:, free], b_free)
    full = torch.zeros(n, dtype=torch.float64)
    full[0], full[free] = y[0], sol
    return full[0::2]


@pytest.mark.parametrize("seed", range(3))
def test_smoother_mean_is_the_batch_least_squares_solution(seed):
    g = torch.Generator().manual_seed(seed)
    r, q = 0.3 ** 2, 0.05 ** 2
    y, _ = _simulate(25, 1, r, q, g)
    xs, _ = cv_kalman_smoother(y, r, q)
    ref = _batch_least_squares(y[:, 0], r, q)
    assert torch.allclose(xs[:, 0], ref, atol=1e-6), (xs[:, 0] - ref).abs().max()
    assert xs[0, 0] == y[0, 0]


@pytest.mark.parametrize("lag", [0, 1, 4, 12])
def test_fixed_lag_is_the_smoother_of_the_series_up_to_t_plus_lag(lag):
    """Frame t of the fixed-lag smoother equals the fixed-interval smoother of y[0 .. t + L]
    at t (independently: the dense batch solution of that prefix); lag 0 is the filter."""
    g = torch.Generator().manual_seed(lag)
    T, r, q = 16, 0.05 ** 2, 0.01 ** 2
    y, _ = _simulate(T, 2, r, q, g)
    x, ll = cv_kalman_smoother(y, r, q, lag=lag)
    assert torch.equal(ll, cv_kalman_smoother(y, r, q)[1])
    for col in range(2):
        ref = torch.stack([y[0, col]] + [  # frame 0 is exact
            _batch_least_squares(y[:min(t + lag, T - 1) + 1, col], r, q)[t]
            for t in range(1, T)])
        assert torch.allclose(x[:, col], ref, atol=1e-6), (lag, col)  # diffuse v_0: 1e8
    if lag >= T - 1:
        assert torch.equal(x, cv_kalman_smoother(y, r, q)[0])


def test_a_longer_lag_is_closer_to_the_truth():
    """On simulated data, each extra frame of look-ahead helps (means over 200 series), and a
    few frames recover most of what the whole clip gives."""
    g = torch.Generator().manual_seed(0)
    r, q = 0.03 ** 2, 0.002 ** 2
    y, x = _simulate(120, 200, r, q, g)
    err = {L: float((cv_kalman_smoother(y, r, q, lag=L)[0] - x)[1:].pow(2).mean().sqrt())
           for L in (0, 1, 2, 4, 8, None)}
    raw = float((y - x)[1:].pow(2).mean().sqrt())
    assert raw > err[0] > err[1] > err[2] > err[4] > err[8] >= err[None] - 1e-12
    assert err[8] - err[None] < 0.15 * (err[0] - err[None])
    sm = KalmanSmoother(measurement_std_deg=math.degrees(0.03),
                        acceleration_std_deg=math.degrees(0.002), lag=2)
    out, info = sm.smooth_theta(y.float())
    assert info["lag"] == 2 and "lag=2" in repr(sm)
    d = out.double()[1:] - cv_kalman_smoother(y, r, q, lag=2)[0][1:]
    assert float((torch.remainder(d + math.pi, 2 * math.pi) - math.pi).abs().max()) < 2e-6


def test_log_likelihood_is_the_gaussian_density_of_frames_2_on_given_frame_1():
    """Explicit joint Gaussian of y_1..y_{T-1} (x_0 known, v_0 diffuse), conditioned on y_1."""
    g = torch.Generator().manual_seed(3)
    T, r, q, V = 12, 0.2 ** 2, 0.1 ** 2, 1e8
    y, _ = _simulate(T, 1, r, q, g)
    # states as a linear map of (v_0, w_1 .. w_{T-1}) plus x_0
    k = 1 + 2 * (T - 1)
    S = torch.zeros(T, 2, k, dtype=torch.float64)
    S[0, 1, 0] = 1.0
    for t in range(1, T):
        S[t] = F @ S[t - 1]
        S[t, :, 1 + 2 * (t - 1):1 + 2 * t] += torch.eye(2, dtype=torch.float64)
    prior = torch.block_diag(torch.tensor([[V]], dtype=torch.float64),
                             *[_q_matrix(q)] * (T - 1))
    Hx = S[1:, 0, :]  # (T-1, k)
    cov = Hx @ prior @ Hx.T + r * torch.eye(T - 1, dtype=torch.float64)
    mean = y[0, 0].expand(T - 1)
    d = y[1:, 0] - mean
    # conditional of y_2.. given y_1
    c11, c12, c22 = cov[0, 0], cov[0, 1:], cov[1:, 1:]
    mu = d[1:] - c12 * d[0] / c11
    C = c22 - torch.outer(c12, c12) / c11
    ref = torch.distributions.MultivariateNormal(torch.zeros_like(mu), C).log_prob(mu)
    _, ll = cv_kalman_smoother(y, r, q)
    assert float(ll[0]) == pytest.approx(float(ref), abs=1e-4)


@pytest.mark.parametrize("seed", range(3))
def test_fit_recovers_the_simulated_noise(seed):
    g = torch.Generator().manual_seed(seed)
    r, q = 0.02 ** 2, 0.004 ** 2
    y, _ = _simulate(150, 20, r, q, g)
    grid = torch.logspace(-8, 0, 49, dtype=torch.float64)
    rh, qh, _ = fit_cv_noise(y, grid, grid, shared=True)
    assert (rh == rh[0]).all() and (qh == qh[0]).all()
    assert 0.8 < math.sqrt(float(rh[0]) / r) < 1.25
    assert 0.7 < math.sqrt(float(qh[0]) / q) < 1.4
    # per column: noisier but around the truth
    rc, qc, ll = fit_cv_noise(y, grid, grid)
    assert 0.7 < math.sqrt(float(rc.median()) / r) < 1.4
    # the grid's log-likelihood is the smoother's at the chosen variances (the grid pass keeps
    # no per-frame moments; it must not change the value)
    assert torch.allclose(ll, cv_kalman_smoother(y, rc, qc)[1], rtol=0, atol=1e-9)


def test_unwrap_angles_removes_two_pi_jumps():
    a = torch.linspace(2.8, 3.8, 11, dtype=torch.float64)
    wrapped = torch.remainder(a + math.pi, 2 * math.pi) - math.pi
    assert (wrapped.diff().abs() > 6).any()
    assert torch.allclose(unwrap_angles(wrapped[:, None])[:, 0], a, atol=1e-12)


@pytest.fixture(scope="module")
def walk():
    return synthesized_sequence({"frames": 60}, "studio", {"image_size": [80, 60]}, seed=0)


def _mpjpe(sk, theta, truth):
    return float((sk(theta.double()).positions - sk(truth.double()).positions)
                 .norm(dim=-1).mean()) * 1000


@pytest.mark.parametrize("seed", range(3))
def test_white_estimate_noise_on_real_motion_is_removed(walk, seed):
    """The truth of a real walk with 3 deg white noise on every rotation DoF (2 cm on the root):
    the smoother, knowing neither, removes most of it and keeps the motion."""
    gt = walk.ground_truth
    sk = gt.build_skeleton()
    truth = gt.theta.double()
    g = torch.Generator().manual_seed(seed)
    noise = math.radians(3.0) * torch.randn(truth.shape, generator=g, dtype=torch.float64)
    noise[:, sk.translation_dofs] *= 0.02 / math.radians(3.0)
    noise[0] = 0
    noisy = sk.clamp(truth + noise)
    sm = KalmanSmoother(skeleton=sk)
    out, info = sm.smooth_theta(noisy)
    before, after = _mpjpe(sk, noisy, truth), _mpjpe(sk, out, truth)
    assert after < 0.6 * before, (before, after)
    assert torch.equal(out[0], noisy[0])
    assert bool(sk.within_limits(out, tol=1e-9).all())
    # the fitted noise is of the order of the one added
    assert 1.5 < info["measurement_std_deg_median"] < 4.5, info
    # the truth itself is smooth: smoothing it changes it little
    clean, info_c = sm.smooth_theta(truth)
    assert _mpjpe(sk, clean, truth) < 5.0
    assert info_c["measurement_std_deg_median"] < 0.5 * info["measurement_std_deg_median"]


def test_euler_branch_jumps_of_a_ball_joint_are_not_motion(walk):
    """The same shoulder rotation written with the other Euler branch on every 4th frame (as a
    particle tracker's estimate may jump between them): smoothed on SO(3) the rotations stay
    what they were; smoothing the angles would average two branches into other rotations."""
    from torchmocap.filters.optim import angles_from_matrix, skeleton_rotation_groups

    sk = walk.ground_truth.build_skeleton().double()
    truth = walk.ground_truth.theta.double()
    (g,) = skeleton_rotation_groups(sk, ["r_shoulder"])
    idx = list(g.indices)
    jumped = truth.clone()
    frames = torch.arange(3, truth.shape[0], 4)
    a = truth[frames][:, idx]
    alt = angles_from_matrix(g.to_matrix, g.matrix(a), a + math.pi)
    assert torch.allclose(g.matrix(alt), g.matrix(a), atol=1e-9)
    assert float((alt - a).abs().max(-1).values.min()) > math.radians(90)
    jumped[frames[:, None], torch.tensor(idx)] = alt
    assert _mpjpe(sk, jumped, truth) < 1e-6  # the same poses
    so3, info = KalmanSmoother(skeleton=sk, clamp_limits=False).smooth_theta(jumped)
    angles, _ = KalmanSmoother(skeleton=sk, clamp_limits=False,
                               rotations="angles").smooth_theta(jumped)
    assert info["rotations"] == "so3"
    assert _mpjpe(sk, so3, truth) < 5.0
    assert _mpjpe(sk, angles, truth) > 4 * _mpjpe(sk, so3, truth)


def test_held_dofs_are_kept_and_left_out_of_the_noise_fit(walk):
    """An upper-body tracker never moves the legs: those DoFs stay exactly as they were and do
    not pull the pooled noise estimate towards zero."""
    gt = walk.ground_truth
    sk = gt.build_skeleton()
    truth = gt.theta.double()
    g = torch.Generator().manual_seed(0)
    noisy = truth + math.radians(3.0) * torch.randn(truth.shape, generator=g,
                                                    dtype=torch.float64)
    noisy[:, sk.translation_dofs] = truth[:, sk.translation_dofs]
    noisy[0] = truth[0]
    noisy = sk.clamp(noisy)
    legs = [d for j in ("l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle")
            for d in sk.joint_dofs(j)]
    held = noisy.clone()
    held[:, legs] = noisy[0, legs]
    sm = KalmanSmoother(skeleton=sk)
    out_all, info_all = sm.smooth_theta(noisy)
    out, info = sm.smooth_theta(held)
    assert torch.equal(out[:, legs], held[:, legs])
    assert info["held_dofs"] == len(legs) + len(sk.translation_dofs) - \
        sum(bool((truth[:, d] != truth[0, d]).any()) for d in sk.translation_dofs)
    # the noise fitted on the moving DoFs is the same as with the legs moving too
    assert info["measurement_std_deg_median"] == pytest.approx(
        info_all["measurement_std_deg_median"], rel=0.5)
    assert info["measurement_std_deg_median"] > 1.5


def test_root_heading_across_pi_and_fixed_noise(walk):
    sk = walk.ground_truth.build_skeleton()
    T = 30
    theta = walk.ground_truth.theta[:T].double().clone()
    yaw = sk.rotation_dofs[0]  # the root's first rotation: no limits
    assert not math.isfinite(float(sk.lower[yaw]))
    ramp = torch.linspace(2.9, 3.6, T, dtype=torch.float64)
    theta[:, yaw] = torch.remainder(ramp + math.pi, 2 * math.pi) - math.pi
    for rotations, tol in (("angles", 1e-3), ("so3", 1e-2)):
        # angles: the ramp is linear, kept; so3: the root's three angles are smoothed as one
        # rotation, the ramp is kept to within a fraction of a degree — never a 2 pi excursion
        out, _ = KalmanSmoother(skeleton=sk, measurement_std_deg=1.0, acceleration_std_deg=0.5,
                                rotations=rotations).smooth_theta(theta)
        d = torch.remainder(out[:, yaw] - theta[:, yaw] + math.pi, 2 * math.pi) - math.pi
        assert float(d.abs().max()) < tol, rotations
        assert float(out[:, yaw].abs().max()) <= math.pi + 1e-12


def test_limits_are_kept_and_counted():
    """A knee flexing fast into its limit and stopping there: the constant-velocity smoother
    overshoots the corner; the overshoot is clamped into the limit and counted."""
    from torchmocap.skeleton import human31
    sk = human31().double()
    T = 40
    knee = sk.dof_index([n for n in sk.dof_names if "knee" in n][0])
    lo = float(sk.lower[knee])
    t = torch.arange(T, dtype=torch.float64)
    clamped = 0
    for seed in range(3):
        g = torch.Generator().manual_seed(seed)
        theta = sk.zero_pose((T,), dtype=torch.float64)
        theta[:, knee] = torch.clamp(lo + torch.clamp(1.2 - 0.12 * t, min=0)
                                     + 0.03 * torch.randn(T, generator=g, dtype=torch.float64),
                                     min=lo)
        out, info = KalmanSmoother(skeleton=sk).smooth_theta(theta)
        assert bool(sk.within_limits(out, tol=1e-12).all())
        assert info["held_dofs"] == sk.num_dofs - 1
        clamped += info["clamped"]
    assert clamped > 0


def test_smooth_keeps_the_filtered_track_and_reports():
    from torchmocap.skeleton import human31
    sk = human31()
    g = torch.Generator().manual_seed(1)
    theta = sk.clamp(0.05 * torch.randn(10, sk.num_dofs, generator=g))
    track = Track(theta=theta, infos=[FrameInfo(t) for t in range(10)], seconds_per_frame=0.1)
    out = KalmanSmoother(skeleton=sk).smooth(track)
    assert torch.equal(out.filtered, theta) and out.theta.dtype == theta.dtype
    rep = out.smoother
    assert out.infos == track.infos and rep["name"] == "kalman"
    assert set(rep["dofs"]) == set(sk.dof_names)
    assert track.smoother is None and track.filtered is None  # the input track is not changed
    # two frames: nothing to smooth, said so
    short, info = KalmanSmoother(skeleton=sk).smooth_theta(theta[:2])
    assert torch.equal(short, theta[:2]) and "reason" in info


@pytest.mark.parametrize("kwargs, match", [
    ({"measurement_std_deg": 0.0}, "measurement_std_deg"),
    ({"acceleration_std_deg": float("nan")}, "acceleration_std_deg"),
    ({"translation_measurement_std": -1.0}, "translation_measurement_std"),
    ({"translation_acceleration_std": True}, "translation_acceleration_std"),
    ({"grid_size": 1}, "grid_size"),
    ({"clamp_limits": 1}, "clamp_limits"),
    ({"per_dof": "yes"}, "per_dof"),
    ({"rotations": "euler"}, "rotations"),
    ({"lag": -1}, "lag"),
    ({"lag": 2.5}, "lag"),
    ({"lag": True}, "lag"),
])
def test_bad_settings_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        KalmanSmoother(**kwargs)


def test_bad_tracks_are_named():
    from torchmocap.skeleton import human31
    sk = human31()
    sm = KalmanSmoother(skeleton=sk)
    with pytest.raises(ValueError, match="track.theta.*finite"):
        sm.smooth_theta(torch.full((5, sk.num_dofs), float("nan")))
    with pytest.raises(ValueError, match="track.theta.*DoFs"):
        sm.smooth_theta(torch.zeros(5, sk.num_dofs + 1))
    with pytest.raises(ValueError, match=r"track.theta.*\(T, D\)"):
        sm.smooth_theta(torch.zeros(5))
    with pytest.raises(ValueError, match="r, q"):
        cv_kalman_smoother(torch.zeros(4, 1, dtype=torch.float64), 0.0, 1.0)
    with pytest.raises(ValueError, match="y: expected"):
        fit_cv_noise(torch.zeros(2, 1), torch.ones(2), torch.ones(2))
    with pytest.raises(ValueError, match="y: expected finite"):
        cv_kalman_smoother(torch.tensor([[0.0], [float("inf")]], dtype=torch.float64), 1.0, 1.0)


@pytest.fixture(scope="module")
def walk8():
    return synthesized_sequence({"frames": 8}, "studio", {"image_size": [80, 60]}, seed=0)


@pytest.mark.parametrize("seed", range(3))
def test_preset_with_the_smoother_tracks_better_than_its_own_filter(walk8, seed):
    """Wired by config into the default tracker: the smoothed track of a few real frames is
    closer to the truth than the filtered one, and both beat holding the first pose."""
    seq = walk8
    cfg = tracker_config("p_prior_refined", ["+smoother@tracker.smoother=kalman",
                                             "tracker.num_particles=30",
                                             "tracker.inference.layers=3",
                                             "tracker.inference.refine.iterations=20"])
    tr = build_tracker(cfg, Runtime.from_sequence(seq), seed=seed)
    assert isinstance(tr.smoother, KalmanSmoother)
    track = tr.run(seq, progress=False)
    sk = seq.ground_truth.build_skeleton()
    gt = seq.ground_truth.theta
    smoothed, filtered = _mpjpe(sk, track.theta[1:], gt[1:]), _mpjpe(sk, track.filtered[1:],
                                                                       gt[1:])
    held = _mpjpe(sk, gt[:1].expand(len(gt) - 1, -1), gt[1:])
    assert smoothed < filtered < held, (smoothed, filtered, held)
