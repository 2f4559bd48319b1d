"""Viterbi smoothing of multi-hypothesis tracks: exact DP, branch recovery, wiring, errors."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchmocap.assembly import Runtime, build_tracker, tracker_config
from torchmocap.filters import (
    FrameInfo,
    KalmanSmoother,
    SmootherChain,
    TemporalPrior,
    Track,
    ViterbiSmoother,
)
from torchmocap.filters.smoothing import viterbi_path


def _brute_force(emissions, transition):
    best, arg = -math.inf, None
    for path in itertools.product(*(range(e.numel()) for e in emissions)):
        s = sum(float(emissions[t][k]) for t, k in enumerate(path))
        s += sum(float(transition(t)[path[t - 1], path[t]]) for t in range(1, len(path)))
        if s > best:
            best, arg = s, list(path)
    return arg, best


@pytest.mark.parametrize("seed", range(6))
def test_viterbi_path_is_the_brute_force_optimum(seed):
    g = torch.Generator().manual_seed(seed)
    T = 5
    sizes = torch.randint(1, 5, (T,), generator=g).tolist()
    em = [torch.randn(k, generator=g, dtype=torch.float64) for k in sizes]
    tr = {t: 2 * torch.randn(sizes[t - 1], sizes[t], generator=g, dtype=torch.float64)
          for t in range(1, T)}
    path, score = viterbi_path(em, lambda t: tr[t])
    ref_path, ref_score = _brute_force(em, lambda t: tr[t])
    assert path == ref_path
    assert score == pytest.approx(ref_score, abs=1e-12)


def test_transition_prior_wraps_rotations_and_scales_translations():
    prior = TemporalPrior.from_stds(2, [0], math.degrees(0.1), 0.4)
    d = torch.tensor([[0.2, 2 * math.pi - 0.1]], dtype=torch.float64)
    lp = prior.log_prob(d, torch.zeros(2))
    # translation 0.2 / 0.4; rotation wrapped to -0.1 / 0.1
    assert float(lp[0]) == pytest.approx(-0.5 * (0.25 + 1.0), rel=1e-12)


def _track(hyps, energies, theta0, weights=None):
    infos = [FrameInfo(0)]
    for t, (H, v) in enumerate(zip(hyps, energies)):
        w = weights[t] if weights is not None else [1.0 / len(H)] * len(H)
        infos.append(FrameInfo(t + 1, hypotheses=H, mode_energy=v, hypothesis_weights=w))
    first = [torch.tensor(theta0, dtype=torch.float32)]
    # the filter's estimate: the mode closest to the previous estimate (a greedy temporal MAP)
    est = first
    for H in hyps:
        Ht = torch.tensor(H, dtype=torch.float32)
        est = est + [Ht[int((Ht - est[-1]).abs().sum(1).argmin())]]
    return Track(theta=torch.stack(est), infos=infos, seconds_per_frame=0.0)


def test_smoother_recovers_the_branch_a_greedy_filter_lost():
    """Two mirror-image branches (+a, -a) of equal energy in frame 1; from frame 2 on only the
    + branch explains the data (the - branch's energy is 3 higher per frame). The greedy filter
    took the - branch in frame 1 (closer to the start) and stays on it; the smoother takes +
    from frame 1 on."""
    a = [0.30, 0.35, 0.40, 0.45, 0.50]
    hyps = [[[0.0, x], [0.0, -x + 0.06 * (t == 0)]] for t, x in enumerate(a)]
    energies = [[0.0, 0.0]] + [[0.0, 3.0]] * 4
    track = _track(hyps, energies, [0.0, 0.0])
    assert track.theta[1, 1] < 0 and track.theta[-1, 1] < 0  # the filter is on the - branch
    sm = ViterbiSmoother(rotation_std_deg=20.0)
    out = sm.smooth(track)
    assert torch.allclose(out.theta[1:, 1], torch.tensor(a)), out.theta
    assert torch.equal(out.filtered, track.theta)
    assert out.smoother["changed_frames"] == 5
    assert track.smoother is None  # the input track is left as it was
    # with a flat emission the transition alone decides: the branch closest to the start
    flat = _track(hyps, [[0.0, 0.0]] * 5, [0.0, 0.0])
    assert torch.equal(sm.smooth(flat).theta, flat.theta)


def test_emission_weights_reads_the_filter_weights():
    hyps = [[[0.0, 0.1], [0.0, -0.1]]]
    track = _track(hyps, [[0.0, 5.0]], [0.0, 0.0], weights=[[0.01, 0.99]])
    assert float(ViterbiSmoother().smooth(track).theta[1, 1]) == pytest.approx(0.1)
    assert float(ViterbiSmoother(emission="weights").smooth(track).theta[1, 1]) == \
        pytest.approx(-0.1)


def test_translation_dofs_use_the_translation_std():
    class Sk:
        translation_dofs = [0]

    # frame 1: (0.5 m, 0) or (0, 0.5 rad): with translation_std 1 m the translation move is
    # cheaper; with 0.01 m the rotation move is
    hyps = [[[0.5, 0.0], [0.0, 0.5]]]
    track = _track(hyps, [[0.0, 0.0]], [0.0, 0.0])
    cheap = ViterbiSmoother(Sk(), rotation_std_deg=20.0, translation_std=1.0).smooth(track)
    dear = ViterbiSmoother(Sk(), rotation_std_deg=20.0, translation_std=0.01).smooth(track)
    assert float(cheap.theta[1, 0]) == pytest.approx(0.5)
    assert float(dear.theta[1, 1]) == pytest.approx(0.5)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="rotation_std_deg"):
        ViterbiSmoother(rotation_std_deg=0.0)
    with pytest.raises(ValueError, match="emission"):
        ViterbiSmoother(emission="likelihood")
    plain = Track(theta=torch.zeros(3, 2), infos=[FrameInfo(0), FrameInfo(1, ess=[1.0]),
                                                  FrameInfo(2)], seconds_per_frame=0)
    with pytest.raises(ValueError, match=r"infos\[1\].*inference=mixture"):
        ViterbiSmoother().smooth(plain)
    bad = _track([[[0.0, 0.1, 0.2]]], [[0.0]], [0.0, 0.0, 0.0])
    bad.theta = bad.theta[:, :2]
    with pytest.raises(ValueError, match=r"hypotheses \(K, 2\)"):
        ViterbiSmoother().smooth(bad)
    nan = _track([[[0.0, 0.1]]], [[float("nan")]], [0.0, 0.0])
    with pytest.raises(ValueError, match="non-finite"):
        ViterbiSmoother().smooth(nan)


def _mirror_track(seed: int, T: int = 40):
    """A smooth 2-DoF angle trajectory; each frame keeps two modes, the truth plus 2 degrees of
    noise and its mirror image (the second DoF negated) plus noise, 0.5 higher in energy. The
    filter switches to the mirror mode at frame 6 (a greedy choice) and stays there."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(1, T, dtype=torch.float64)
    truth = torch.stack([0.4 * torch.sin(0.08 * t), 0.6 * torch.sin(0.05 * t + 0.2)], 1)
    noise = math.radians(2.0)
    a = truth + noise * torch.randn(truth.shape, generator=g, dtype=torch.float64)
    b = truth * torch.tensor([1.0, -1.0], dtype=torch.float64) + noise * torch.randn(
        truth.shape, generator=g, dtype=torch.float64)
    hyps = [[a[k].tolist(), b[k].tolist()] for k in range(T - 1)]
    track = _track(hyps, [[0.0, 0.5]] * (T - 1), [0.0, 0.0])
    track.theta = torch.cat([track.theta[:1], torch.where(
        (torch.arange(1, T) >= 6)[:, None], b.float(), a.float())])
    return track, torch.cat([torch.zeros(1, 2, dtype=torch.float64), truth])


@pytest.mark.parametrize("seed", range(3))
def test_chain_picks_the_modes_then_removes_their_jitter(seed):
    track, truth = _mirror_track(seed)
    viterbi, kalman = ViterbiSmoother(rotation_std_deg=10.0), KalmanSmoother()
    chain = SmootherChain({"viterbi": viterbi, "kalman": kalman})
    out = chain.smooth(track)

    def err(theta):
        return float((theta.double()[1:] - truth[1:]).abs().mean())

    # the chain is the composition of its stages, and reports the tracker's own estimates
    ref = kalman.smooth(viterbi.smooth(track))
    assert torch.equal(out.theta, ref.theta)
    assert torch.equal(out.filtered, track.theta)
    rep = out.smoother
    assert rep["name"] == "viterbi+kalman"
    assert [r["name"] for r in rep["stages"]] == ["viterbi", "kalman"]
    assert torch.equal(rep["stages"][0]["theta"], viterbi.smooth(track).theta)
    assert torch.equal(rep["stages"][1]["theta"], out.theta)
    assert rep["changed_frames"] == int((out.theta != track.theta).any(-1).sum())
    assert track.smoother is None  # the input track is left as it was
    # the filter is on the mirror branch; Viterbi gets the branch back (the noise stays);
    # the Kalman stage removes much of the noise; Kalman alone smooths across the wrong branch
    e_filter, e_vit, e_chain = err(track.theta), err(viterbi.smooth(track).theta), err(out.theta)
    e_kalman = err(kalman.smooth(track).theta)
    noise = math.radians(2.0) * math.sqrt(2 / math.pi)  # mean |N(0, 2 deg)|
    assert e_filter > 5 * noise and e_kalman > 5 * noise
    assert e_vit == pytest.approx(noise, rel=0.3)
    assert e_chain < 0.7 * e_vit


def test_chain_settings_are_checked_and_named():
    with pytest.raises(ValueError, match="stages"):
        SmootherChain([])
    with pytest.raises(TypeError, match=r"stages\['kalman'\].*Smoother.*dict"):
        SmootherChain({"viterbi": ViterbiSmoother(), "kalman": {"per_dof": True}})
    with pytest.raises(TypeError, match=r"stages\['1'\].*chain inside a chain"):
        SmootherChain([KalmanSmoother(), SmootherChain([KalmanSmoother()])])
    from torchmocap.evaluation import smoother_report

    rep = SmootherChain([ViterbiSmoother(), KalmanSmoother()]).smooth(_mirror_track(0)[0])
    clean = smoother_report(rep.smoother)
    assert "modes" in rep.smoother["stages"][0]  # the per-frame modes are kept...
    assert "modes" not in clean["stages"][0] and "dofs" in clean["stages"][1]  # ...not in JSON
    assert all("theta" not in r for r in clean["stages"])


@pytest.fixture(scope="module")
def walk_mono():
    from torchmocap.data.synthetic.clips import synthesized_sequence

    seq = synthesized_sequence({"name": "walk", "path": None, "frames": 5}, "monocular",
                               {"silhouettes.enabled": False}, seed=0)
    return seq, Runtime.from_sequence(seq)


def test_tracker_with_smoother_returns_the_map_mode_sequence(walk_mono):
    seq, rt = walk_mono
    ov = ["tracker.num_particles=24", "tracker.inference.components=3",
          "+smoother@tracker.smoother=viterbi"]
    tr = build_tracker(tracker_config("kjs", ov), rt, seed=1)
    assert isinstance(tr.smoother, ViterbiSmoother)
    track = tr.run(seq, progress=False)
    plain = build_tracker(tracker_config("kjs", ov[:2]), rt, seed=1).run(seq, progress=False)
    assert torch.equal(track.filtered, plain.theta)  # the smoother does not touch the filter
    theta, path, score = tr.smoother.path(plain)
    assert torch.equal(track.theta, theta)
    # every smoothed pose is one of its frame's hypotheses, and the chosen sequence scores at
    # least as high as the filter's own choices
    for t in range(1, track.theta.shape[0]):
        H = torch.tensor(track.infos[t].hypotheses, dtype=torch.float32)
        assert (H - track.theta[t]).abs().amax(1).min() == 0
    states, scores = tr.smoother.candidates(plain)
    std = torch.full((theta.shape[1],), math.radians(tr.smoother.rotation_std_deg),
                     dtype=torch.float64)
    std[:3] = tr.smoother.translation_std

    def log_prior(d):  # written out: wrapped rotations, Gaussian per DoF
        d = torch.cat([d[:3], torch.atan2(torch.sin(d[3:]), torch.cos(d[3:]))])
        return float(-0.5 * ((d / std) ** 2).sum())

    filt = [0] + [int((s.float() - plain.theta[t]).abs().amax(1).argmin())
                  for t, s in enumerate(states) if t]
    f_score = sum(float(scores[t][k]) for t, k in enumerate(filt)) + sum(
        log_prior(states[t][filt[t]] - states[t - 1][filt[t - 1]]) for t in range(1, len(filt)))
    assert score >= f_score - 1e-9


def test_smoother_needs_a_multi_hypothesis_inference(walk_mono):
    _, rt = walk_mono
    with pytest.raises(ValueError, match="smoother.*inference=mixture.*AnnealedInference"):
        build_tracker(tracker_config("g", ["+smoother@tracker.smoother=viterbi"]), rt)


def test_chain_config_composes_both_stages_and_checks_the_inference(walk_mono):
    seq, rt = walk_mono
    ov = ["tracker.num_particles=24", "tracker.inference.components=3",
          "+smoother@tracker.smoother=viterbi_kalman",
          "tracker.smoother.stages.kalman.per_dof=true"]
    tr = build_tracker(tracker_config("kjs", ov), rt, seed=1)
    assert isinstance(tr.smoother, SmootherChain)
    vit, kal = tr.smoother.stages
    assert isinstance(vit, ViterbiSmoother) and isinstance(kal, KalmanSmoother)
    assert kal.per_dof and kal.ball_groups  # the stage got the tracker's skeleton
    track = tr.run(seq, progress=False)
    plain = build_tracker(tracker_config("kjs", ov[:2]), rt, seed=1).run(seq, progress=False)
    assert torch.equal(track.filtered, plain.theta)
    assert torch.equal(track.theta, kal.smooth(vit.smooth(plain)).theta)
    # the Viterbi stage's requirement is checked when the tracker is assembled
    with pytest.raises(ValueError, match="smoother.*inference=mixture"):
        build_tracker(tracker_config("g", ["+smoother@tracker.smoother=viterbi_kalman"]), rt)
