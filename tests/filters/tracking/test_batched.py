"""Batched tracking (torchmocap.filters.tracking.batched): the lockstep scheduler batches the tasks'
energy requests and keeps errors where they belong; a seed's energies inside a batch equal its
energies alone (to float rounding), so B seeds tracked in one batch agree with the B separate
runs on a short horizon (tracker P: nothing amplifies the last bits); groups do not leak into
each other (a corrupted sequence beside a clean one leaves the clean tracks as they are alone);
invalid groupings are refused."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torchmocap.assembly import Runtime, build_tracker, tracker_config
from torchmocap.data.synthetic.clips import synthesized_sequence
from torchmocap.filters.tracking.batched import BatchGroup, Lockstep, track_groups, track_seeds
from torchmocap.likelihoods.base import FrameEnergy

SMALL = ["tracker.num_particles=16", "tracker.inference.layers=2"]
ATOL = 2e-3  # radians: a batch of B x P particles may round the last bits differently (1e-6
#               measured after 3 frames)


@pytest.fixture(scope="module")
def walk():
    return synthesized_sequence({"frames": 4}, "studio", {"image_size": [80, 60]}, seed=0)


def _tracker(seq, overrides=SMALL, seed=0):
    return build_tracker(tracker_config("p", list(overrides)), Runtime.from_sequence(seq),
                         seed=seed)


def _separate(tracker, seq, seed):
    tracker.seed = seed
    return tracker.run(seq, progress=False).theta


class TestLockstep:
    def test_smoke(self):
        calls = []

        def fn(x):
            calls.append(x.shape[0])
            return x.sum(-1)

        def job(lock, i, n):
            def run():
                out = []
                for k in range(2):
                    x = torch.full((n, 3), float(i + 10 * k))
                    out.append(lock.request(i, "energy", fn, x))
                return out
            return run

        with Lockstep(3) as lock:
            res = lock.run([job(lock, i, n) for i, n in enumerate((2, 3, 4))])
        assert calls == [9, 9]  # one evaluation per round for all three tasks
        for i, n in enumerate((2, 3, 4)):
            for k in range(2):
                assert torch.equal(res[i][k], torch.full((n,), 3.0 * (i + 10 * k)))

    def test_max_batch(self):
        calls = []

        def fn(x):
            calls.append(x.shape[0])
            return x[:, 0] * 2

        with Lockstep(3, max_batch=4) as lock:
            res = lock.run([(lambda i=i, n=n: lock.request(i, "k", fn,
                                                           torch.arange(n * 1.0)[:, None]))
                            for i, n in enumerate((2, 3, 4))])
        assert calls == [4, 4, 1]
        for r, n in zip(res, (2, 3, 4)):
            assert torch.equal(r, 2 * torch.arange(n * 1.0))
        with pytest.raises(ValueError, match="max_batch"):
            Lockstep(2, max_batch=0)

    def test_threads_follow_the_scheduler(self):
        """A thread count set between rounds (the ThreadGovernor) reaches the task threads."""
        with Lockstep(2) as lock:
            assert lock.run([torch.get_num_threads] * 2) == [1, 1]
            torch.set_num_threads(2)
            assert lock.run([torch.get_num_threads] * 2) == [2, 2]
            torch.set_num_threads(1)
            assert lock.run([torch.get_num_threads] * 2) == [1, 1]

    def test_cardinality(self):
        """Idle tasks, tasks that never ask, and keys evaluated apart."""
        seen = []

        def fn(x):
            seen.append(tuple(x[:, 0].tolist()))
            return x[:, 0]

        with Lockstep(4) as lock:
            res = lock.run([
                lambda: lock.request(0, "a", fn, torch.tensor([[1.0]])),
                None,
                lambda: "no energy",
                lambda: lock.request(3, "b", fn, torch.tensor([[4.0]])),
            ])
        assert res[1] is None and res[2] == "no energy"
        assert float(res[0]) == 1.0 and float(res[3]) == 4.0
        assert sorted(seen) == [(1.0,), (4.0,)]

    def test_exception(self):
        def bad_energy(x):
            raise ValueError("energy: NaN")

        with Lockstep(2) as lock:
            with pytest.raises(ValueError, match="energy: NaN"):
                lock.run([lambda: lock.request(0, "k", bad_energy, torch.ones(1, 2)),
                          lambda: lock.request(1, "k", bad_energy, torch.ones(1, 2))])

            def fails():
                raise KeyError("task 0")

            with pytest.raises(KeyError, match="task 0"):
                lock.run([fails,
                          lambda: lock.request(1, "k", lambda x: x.sum(-1), torch.ones(1, 2))])
            # usable after a failed round
            assert lock.run([lambda: 1, lambda: 2]) == [1, 2]
        with pytest.raises(ValueError, match="size"):
            Lockstep(0)


class TestTrackSeeds:
    def test_feature_equals_separate_runs(self, walk, monkeypatch):
        """Track b of a batch is the separate run with seed b, and the energy really saw the
        particles of all seeds at once."""
        sizes = []
        call = FrameEnergy.__call__

        def spy(self, theta, *a, **k):
            sizes.append(int(theta.shape[0]))
            return call(self, theta, *a, **k)

        tr = _tracker(walk)
        seeds = [0, 5, 7]
        monkeypatch.setattr(FrameEnergy, "__call__", spy)
        tracks = track_seeds(tr, walk, seeds, progress=False)
        monkeypatch.undo()
        assert sizes.count(3 * 16) >= 2 * 3  # 2 layers x 3 frames, all seeds in one batch
        assert all(t.theta.shape == (4, tr.skeleton.num_dofs) for t in tracks)
        assert all(t.infos[1].batch_size == 3 for t in tracks)
        alone = [_separate(tr, walk, s) for s in seeds]
        for b, theta in enumerate(alone):
            torch.testing.assert_close(tracks[b].theta, theta, atol=ATOL, rtol=0)
        # distinct seeds give distinct tracks (the groups are not one track repeated)
        assert (tracks[0].theta[1:] - tracks[1].theta[1:]).abs().max() > 10 * ATOL

    @pytest.mark.parametrize("preset", ["p", "p_prior_refined"])
    def test_energy_rows_equal_alone(self, walk, preset):
        """What a batch promises on any CPU: the energy of a seed's particles evaluated inside
        a batch of several seeds equals their energy evaluated alone, to float rounding."""
        tr = _tracker(walk, [] if preset != "p" else SMALL)
        gen = torch.Generator().manual_seed(0)
        truth = walk.ground_truth.theta[1]
        thetas = [truth + 0.05 * torch.randn(16, truth.shape[-1], generator=gen)
                  for _ in range(3)]
        energy = tr.frame_energy(walk.frame(1))
        with torch.no_grad():
            alone = [energy(t) for t in thetas]
            with Lockstep(3) as lock:
                batched = lock.run([(lambda i=i: lock.request(i, "e", energy, thetas[i]))
                                    for i in range(3)])
        for a, b in zip(alone, batched):
            assert a.shape == (16,) and torch.isfinite(a).all()
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-5)
        assert (alone[0] - alone[1]).abs().max() > 1e-3  # distinct particles, distinct energies

    def test_feature_sir(self, walk):
        """The same for another inference (SIR: weights carried between frames per group)."""
        tr = _tracker(walk, ["tracker.num_particles=16", "inference@tracker.inference=sir"])
        tracks = track_seeds(tr, walk, [1, 2], progress=False)
        for b, s in enumerate([1, 2]):
            torch.testing.assert_close(tracks[b].theta, _separate(tr, walk, s), atol=ATOL,
                                       rtol=0)

    def test_groups_do_not_leak(self, walk):
        """A corrupted sequence tracked beside a clean one: the clean tracks are those of the
        clean runs alone, the corrupted one is not."""
        sil = walk.silhouettes.clone()
        sil[1:] = ~sil[1:]  # every later frame's masks inverted
        bad = dataclasses.replace(walk, silhouettes=sil)
        clean_tr, bad_tr = _tracker(walk), _tracker(bad)
        tracks = track_groups([BatchGroup(bad_tr, bad, 0), BatchGroup(clean_tr, walk, 0),
                               BatchGroup(clean_tr, walk, 3)], progress=False)
        torch.testing.assert_close(tracks[1].theta, _separate(clean_tr, walk, 0), atol=ATOL,
                                   rtol=0)
        torch.testing.assert_close(tracks[2].theta, _separate(clean_tr, walk, 3), atol=ATOL,
                                   rtol=0)
        torch.testing.assert_close(tracks[0].theta, _separate(bad_tr, bad, 0), atol=ATOL,
                                   rtol=0)
        assert (tracks[0].theta[1:] - tracks[1].theta[1:]).abs().max() > 10 * ATOL

    def test_exception(self, walk):
        tr = _tracker(walk)
        other = dataclasses.replace(walk)
        with pytest.raises(ValueError, match="one tracker per sequence"):
            track_groups([BatchGroup(tr, walk, 0), BatchGroup(tr, other, 1)], progress=False)
        with pytest.raises(ValueError, match="seeds"):
            track_seeds(tr, walk, [], progress=False)
        with pytest.raises(ValueError, match="seeds"):
            track_seeds(tr, walk, [0, 1.5], progress=False)
        with pytest.raises(ValueError, match="theta0"):
            track_groups([BatchGroup(tr, walk, 0),
                          BatchGroup(tr, walk, 1, theta0=walk.ground_truth.theta[1])],
                         progress=False)
        with pytest.raises(TypeError, match="BatchGroup"):
            track_groups([(tr, walk, 0)], progress=False)
        tr.refine_first_frame = True
        with pytest.raises(ValueError, match="refines the first frame"):
            track_seeds(tr, walk, [0, 1], progress=False)

    def test_callbacks(self, walk):
        seen = []
        track_seeds(_tracker(walk), walk, [0, 1], progress=False,
                    callbacks=[lambda states, infos: seen.append(
                        ([s.frame for s in states], [i.frame for i in infos]))])
        assert seen == [([t, t], [t, t]) for t in (1, 2, 3)]
