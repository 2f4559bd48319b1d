"""Training learned likelihoods: gradients through inference, objectives, the loop, checkpoints."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torchmocap.learning import (
    NegativeSettings,
    build_clip_data,
    joint_error,
    load_checkpoint,
    ranking_loss,
    save_checkpoint,
    stop_gradient_resample,
    unrolled_annealing,
    unrolled_descent,
)
from torchmocap.learning.trainer import EndToEndSettings, Trainer, TrainSettings
from torchmocap.likelihoods import (
    ArchitectureMismatchError,
    LearnedFeatureLikelihood,
    LearnedRenderLikelihood,
    Poses,
)

NEG = NegativeSettings(num_particles=20, proposal_negatives=6, hard_negatives=4, stride=2)


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    cache = tmp_path_factory.mktemp("train_cache")
    train = build_clip_data({"name": "w", "path": None, "frames": 7}, "outdoor", seed=0,
                            negatives=NEG, cache_dir=cache)
    val = build_clip_data({"name": "v", "path": None, "start": 1.5, "frames": 5}, "outdoor",
                          seed=1, negatives=NEG, cache_dir=cache)
    return train, val, cache


def _term(clip, kind="features", seed=0, **kw):
    torch.manual_seed(seed)
    rt = clip.runtime
    if kind == "render":
        return LearnedRenderLikelihood(rt.body, rt.rig, size=(24, 18), **kw)
    return LearnedFeatureLikelihood(rt.body, rt.rig, **kw)


def _energy(term, clip, frame):
    obs = term.prepare(frame)
    sk = clip.runtime.skeleton
    return lambda theta: term.energy(Poses(theta, sk), obs)


def _assert_all_grads(term):
    for name, p in term.net.named_parameters():
        assert p.grad is not None, name
        assert bool(torch.isfinite(p.grad).all()), name
        assert float(p.grad.abs().sum()) > 0, name


def test_data(clips):
    train, val, cache = clips
    assert len(train.frames) == 3  # frames 1, 3, 5 of 7
    f = train.frames[0]
    assert f.negatives.shape == (NEG.proposal_negatives + NEG.hard_negatives, 31)
    assert f.frame.theta is None  # the tracker's view: no ground truth
    again = build_clip_data({"name": "w", "path": None, "frames": 7}, "outdoor", seed=0,
                            negatives=NEG, cache_dir=cache)  # from the cache
    assert torch.equal(again.frames[1].negatives, train.frames[1].negatives)


class TestGradientsThroughOneTrackerStep:
    @pytest.mark.parametrize("kind", ["features", "render"])
    def test_local(self, clips, kind):
        """Unrolled descent: the result's error is differentiable in every parameter."""
        train = clips[0]
        term = _term(train, kind)
        f = train.frames[0]
        sk = train.runtime.skeleton
        x = unrolled_descent(_energy(term, train, f.frame), f.negatives[:2], steps=3, lr=0.05,
                             lower=sk.lower, upper=sk.upper)
        joint_error(sk, x, f.truth).sum().backward()
        _assert_all_grads(term)

    def test_annealed(self, clips):
        """Annealing layers with stop-gradient resampling: every parameter gets a gradient."""
        train = clips[0]
        term = _term(train)
        f = train.frames[0]
        tr = train.tracker
        from torchmocap.proposals.base import ProposalContext

        ctx = ProposalContext(previous=f.negatives[0], sensors=tr._sensors(f.frame),
                              sensor_valid=f.frame.imu_valid, frame=f.frame)
        g = torch.Generator().manual_seed(0)
        est, info = unrolled_annealing(_energy(term, train, f.frame), tr.proposal, ctx, 16,
                                       layers=3, generator=g)
        assert est.shape == (31,) and len(info["beta"]) == 3
        joint_error(train.runtime.skeleton, est, f.truth).backward()
        _assert_all_grads(term)


class TestStopGradientResampling:
    def test_forward_is_unchanged(self):
        theta = torch.tensor(0.7, requires_grad=True)
        lw = theta * torch.linspace(-1, 1, 8)
        idx, carried = stop_gradient_resample(lw, torch.Generator().manual_seed(0))
        assert idx.shape == (8,) and torch.equal(carried.detach(), torch.zeros(8))
        carried.sum().backward()
        assert theta.grad is not None and float(theta.grad.abs()) > 0

    def test_unbiased_gradient(self):
        """E over resampling of ∇(mean over the resampled set of exp(carried) f) equals
        ∇ Σ w f: the carried log weights (zero in value) bring the ancestors' weight gradient
        to later layers. (Forgetting them — plain indexing — gives a zero gradient.)"""
        theta = torch.tensor(0.3, requires_grad=True)
        x = torch.linspace(-2, 2, 6)
        f = x**2 + x
        exact = torch.autograd.grad((torch.softmax(-theta * x, 0) * f).sum(), theta)[0]
        g = torch.Generator().manual_seed(1)
        acc = 0.0
        n = 4000
        for _ in range(n):
            idx, carried = stop_gradient_resample(-theta * x, g)
            est = (carried.exp() * f[idx]).mean()
            acc += torch.autograd.grad(est, theta)[0]
        assert float(acc / n) == pytest.approx(float(exact), rel=0.08)


def test_ranking_loss():
    e = torch.tensor([0.0, 1.0, 2.0], requires_grad=True)
    err = torch.tensor([0.0, 0.05, 0.1])
    loss = ranking_loss(e, err)
    loss.backward()
    assert e.grad[0] > 0  # lowering the truth's energy lowers the loss
    # energies ordered like the target (0, 2.5, 5 = errors / err_scale) minimise the loss
    assert float(ranking_loss(torch.tensor([0.0, 2.5, 5.0]), err)) < float(loss.detach())
    with pytest.raises(ValueError, match="err_scale"):
        ranking_loss(e, err, err_scale=0.0)


def _settings(**kw):
    s = TrainSettings(epochs=3, batch_size=2, lr=0.01, max_negatives=10, seed=0,
                      schedule="none")
    return dataclasses.replace(s, **kw)


def _train(clips, tmp_path, settings, kind="features", name="run", resume=None):
    train, val, _ = clips
    term = _term(train, kind, seed=settings.seed)
    t = Trainer(term, [train], [val], settings, tmp_path / name, tensorboard=True,
                progress=False)
    if resume is not None:
        t.resume(resume)
    t.fit()
    return t


class TestTraining:
    def test_ranking_loss_decreases(self, clips, tmp_path):
        t = _train(clips, tmp_path, _settings(epochs=6, lr=0.02))
        losses = [m["train_loss"] for m in t.metrics if "train_loss" in m]
        assert losses[-1] < losses[0]
        assert (tmp_path / "run" / "metrics.csv").is_file()
        assert any((tmp_path / "run" / "tb").iterdir())  # TensorBoard events
        assert (tmp_path / "run" / "checkpoints" / "last.pt").is_file()

    def test_end_to_end_loss_decreases(self, clips, tmp_path):
        s = _settings(objective="end_to_end", epochs=4, lr=0.02,
                      end_to_end=EndToEndSettings(mode="descent", steps=3, lr=0.05))
        t = _train(clips, tmp_path, s)
        losses = [m["train_e2e_mm"] for m in t.metrics if "train_e2e_mm" in m]
        assert len(losses) == 4 and losses[-1] < losses[0]

    def test_reproducible(self, clips, tmp_path):
        a = _train(clips, tmp_path, _settings(epochs=2), name="a")
        b = _train(clips, tmp_path, _settings(epochs=2), name="b")
        for (k, v), w in zip(a.term.net.state_dict().items(), b.term.net.state_dict().values()):
            assert torch.equal(v, w), k

    def test_resume_equals_uninterrupted(self, clips, tmp_path):
        full = _train(clips, tmp_path, _settings(epochs=2), name="full")
        first = _train(clips, tmp_path, _settings(epochs=1), name="half")
        train, val, _ = clips
        term = _term(train, seed=123)  # the checkpoint replaces this initialisation
        t = Trainer(term, [train], [val], _settings(epochs=2), tmp_path / "resumed",
                    tensorboard=False, progress=False)
        t.resume(first.out / "checkpoints" / "last.pt")
        assert t.epoch == 1 and len(t.metrics) == 2
        t.fit()
        # the same data order and optimiser state: the same weights
        for (k, v), w in zip(full.term.net.state_dict().items(), t.term.net.state_dict().values()):
            torch.testing.assert_close(v, w, rtol=1e-5, atol=1e-6, msg=k)

    def test_checkpoint_round_trip_and_mismatch(self, clips, tmp_path):
        train = clips[0]
        t = _train(clips, tmp_path, _settings(epochs=1))
        ck = t.out / "checkpoints" / "last.pt"
        f = train.frames[0]
        x = torch.cat([f.truth[None], f.negatives])
        loaded = LearnedFeatureLikelihood(train.runtime.body, train.runtime.rig, weights=str(ck))
        with torch.no_grad():
            a = _energy(t.term, train, f.frame)(x)
            b = _energy(loaded, train, f.frame)(x)
        assert torch.equal(a, b)
        other = _term(train, hidden=4)
        with pytest.raises(ArchitectureMismatchError, match="hidden: file 8, config 4"):
            load_checkpoint(ck, other)
        exported = t.export(tmp_path / "w.pt")
        assert exported.stat().st_size < ck.stat().st_size
        again = LearnedFeatureLikelihood(train.runtime.body, train.runtime.rig,
                                         weights=str(exported))
        with torch.no_grad():
            assert torch.equal(_energy(again, train, f.frame)(x), b)

    def test_save_checkpoint_with_optimiser(self, clips, tmp_path):
        train = clips[0]
        term = _term(train)
        opt = torch.optim.Adam(term.net.parameters(), lr=1e-3)
        f = train.frames[0]
        _energy(term, train, f.frame)(f.negatives[:3]).sum().backward()
        opt.step()
        p = save_checkpoint(tmp_path / "c.pt", term, optimizer=opt, epoch=3, step=7)
        opt2 = torch.optim.Adam(_term(train, seed=5).net.parameters(), lr=1e-3)
        term2 = _term(train, seed=5)
        opt2 = torch.optim.Adam(term2.net.parameters(), lr=1e-3)
        payload = load_checkpoint(p, term2, optimizer=opt2)
        assert payload["epoch"] == 3 and payload["step"] == 7
        assert opt2.state_dict()["state"][0]["step"] == opt.state_dict()["state"][0]["step"]

    def test_exception(self):
        with pytest.raises(ValueError, match="objective.name"):
            TrainSettings(objective="magic").check()
        with pytest.raises(ValueError, match="optim.name"):
            TrainSettings(optimizer="lion").check()
        if not torch.cuda.is_available():
            with pytest.raises(ValueError, match="CUDA is not available"):
                TrainSettings(device="cuda").check()
        assert math.isfinite(TrainSettings().lr)
