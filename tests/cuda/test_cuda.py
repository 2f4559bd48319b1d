"""The trackers on a CUDA GPU (marker ``cuda``; skipped when no GPU is present — the only skip
of the suite). ``python -m pytest -m cuda`` runs just these.

Every preset kind runs a few frames with ``tracker.to("cuda")`` on a CPU sequence (the tracker
moves each frame to its device): the estimates, particles and the generator live on the GPU and
the track stays close to the truth; batched seeds run there too. On a machine without a GPU,
tests/test_device.py proves the same code device-agnostic on the CPU.
"""

from __future__ import annotations

import pytest
import torch

from torchmocap.assembly import Runtime, build_tracker, tracker_config
from torchmocap.data.synthetic.clips import synthesized_sequence

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")]

CUDA = torch.device("cuda")
PRESETS = [
    ("p", "studio", ["tracker.num_particles=64", "tracker.inference.layers=4"]),
    ("g", "studio", ["tracker.num_particles=64", "tracker.inference.layers=4"]),
    ("gs", "studio", ["tracker.num_particles=64", "tracker.inference.layers=4"]),
    ("rs", "studio", ["tracker.num_particles=32", "tracker.inference.layers=3"]),
    ("p", "studio", ["tracker.num_particles=64", "inference@tracker.inference=sir"]),
    ("ls", "studio", ["tracker.inference.iterations=5"]),
    ("p_prior_refined", "studio", ["tracker.num_particles=64", "tracker.inference.layers=4",
                                   "tracker.inference.refine.iterations=5"]),  # the default
    ("hauberg_spatial", "stereo", ["tracker.num_particles=32"]),
    ("hauberg_silhouette", "stereo", ["tracker.num_particles=32"]),
    ("hauberg_depth", "stereo", ["tracker.num_particles=32"]),
    ("kjs", "monocular", ["tracker.num_particles=16"]),
    ("kjs", "monocular", ["tracker.num_particles=16", "+smoother@tracker.smoother=viterbi"]),
    ("p", "studio", ["tracker.num_particles=32", "tracker.inference.layers=3",
                     "+smoother@tracker.smoother=kalman"]),
    ("kjs", "monocular", ["tracker.num_particles=16",
                          "+smoother@tracker.smoother=viterbi_kalman"]),
    ("p", "studio", ["tracker.num_particles=32", "tracker.inference.layers=3",
                     "+smoother@tracker.smoother=kalman", "tracker.smoother.lag=1"]),
]
IDS = ["p", "g", "gs", "rs", "p_sir", "ls", "p_prior_refined", "hauberg_spatial",
       "hauberg_silhouette", "hauberg_depth", "kjs", "kjs_viterbi", "p_kalman",
       "kjs_viterbi_kalman", "p_kalman_lag"]


@pytest.fixture(scope="module")
def sequences():
    cache = {}

    def get(scenario):
        if scenario not in cache:
            cache[scenario] = synthesized_sequence({"frames": 4}, scenario,
                                                   {"image_size": [160, 120]}, seed=0)
        return cache[scenario]

    return get


@pytest.mark.parametrize("name,scenario,overrides", PRESETS, ids=IDS)
def test_tracker_on_cuda(name, scenario, overrides, sequences):
    seq = sequences(scenario)
    tr = build_tracker(tracker_config(name, overrides), Runtime.from_sequence(seq),
                       seed=0).to(CUDA)
    assert tr.device.type == "cuda"
    track = tr.run(seq, progress=False)
    assert track.theta.device.type == "cuda" and track.theta.shape[0] == seq.num_frames
    assert bool(torch.isfinite(track.theta).all())
    # close to the truth: a broken component on the GPU (wrong device, garbage) would not be
    truth = seq.ground_truth.positions[1:].to(CUDA, torch.float32)
    err = (tr.skeleton(track.theta[1:]).positions - truth).norm(dim=-1).mean()
    assert float(err) < 0.25, float(err)


def test_step_state_on_cuda(sequences):
    seq = sequences("studio")
    tr = build_tracker(tracker_config("p", PRESETS[0][2]), Runtime.from_sequence(seq),
                       seed=0).to(CUDA)
    tracking = seq.imu.tracking.nonzero()[:, 0]
    st = tr.init(seq.ground_truth.theta[0], tr.observe(seq.frame(0), tracking))
    st, est, _ = tr.step(st, tr.observe(seq.frame(1), tracking))
    assert est.device.type == "cuda" and st.particles.device.type == "cuda"
    assert st.log_weights.device.type == "cuda"
    # the generator is the GPU's: its state resumes a CUDA generator
    g = torch.Generator(device=CUDA)
    g.set_state(st.generator_state)
    # the same seed gives the same track on the GPU too
    st2 = tr.init(seq.ground_truth.theta[0], tr.observe(seq.frame(0), tracking))
    _, est2, _ = tr.step(st2, tr.observe(seq.frame(1), tracking))
    torch.testing.assert_close(est, est2)


def test_batched_seeds_on_cuda(sequences):
    from torchmocap.filters.tracking.batched import track_seeds

    seq = sequences("studio")
    tr = build_tracker(tracker_config("p", PRESETS[0][2]), Runtime.from_sequence(seq),
                       seed=0).to(CUDA)
    tracks = track_seeds(tr, seq, [0, 1, 2], progress=False)
    for s, t in zip([0, 1, 2], tracks):
        assert t.theta.device.type == "cuda"
        tr.seed = s
        torch.testing.assert_close(t.theta, tr.run(seq, progress=False).theta, atol=5e-3,
                                   rtol=0)


def test_ess_beta_on_the_gpu_equals_the_cpu_solver():
    """A GPU tensor takes the torch solver (CPU tensors the numpy one): same β."""
    from torchmocap.filters.optim.schedules import ess_target_beta

    v = torch.randn(3, 200, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    gpu = ess_target_beta(v.to(CUDA), 0.5)
    assert gpu.beta.device.type == "cuda"
    torch.testing.assert_close(gpu.beta.cpu(), ess_target_beta(v, 0.5).beta, rtol=1e-12, atol=0)
