"""The thread policy (torchmocap.threads): the pure decision from cores, load and launcher
settings; the load measurement's arithmetic; the governor that re-applies it between frames;
the CLI records it; the tracker's per-frame callbacks."""

from __future__ import annotations

import pytest
import torch

from torchmocap import threads
from torchmocap.threads import (
    CpuSample,
    ThreadGovernor,
    apply_thread_policy,
    busy_between,
    choose_threads,
    launcher_share,
    parse_threads,
)


class TestChooseThreads:
    @pytest.mark.parametrize("cores,busy,jobs,per_job,expected", [
        (2, 0.0, 1, None, 2),     # idle machine: every core
        (2, 0.97, 1, None, 1),    # one busy loop beside: stay off its core
        (2, 0.3, 1, None, 2),     # light background noise does not count
        (2, 1.9, 1, None, 1),     # everything busy: still one thread
        (16, 3.2, 1, None, 13),   # three busy cores of sixteen
        (16, 0.0, 4, None, 4),    # joblib n_jobs=4 on 16 cores: 4 each
        (16, 0.0, 32, None, 1),   # more parallel jobs than cores: 1 each
        (16, 0.0, 1, 2, 2),       # submitit cpus_per_task=2
        (8, 6.0, 2, None, 2),     # the smaller of the job's share and the free cores
        (2, float("nan"), 1, None, 2),
    ])
    def test_feature(self, cores, busy, jobs, per_job, expected):
        assert choose_threads(cores, busy, jobs, per_job).threads == expected

    def test_explicit_choice_wins(self):
        assert choose_threads(2, 1.9, requested=2).threads == 2
        assert choose_threads(2, 1.9, requested="3").threads == 3
        c = choose_threads(16, 0.0, jobs=4, omp_num_threads="1")
        assert c.threads == 1 and "OMP_NUM_THREADS" in c.reason
        assert choose_threads(4, 0.0, requested=2, omp_num_threads="1").threads == 2
        # a malformed environment value is ignored, not fatal
        assert choose_threads(2, 0.0, omp_num_threads="lots").threads == 2

    def test_reason(self):
        r = choose_threads(2, 0.97).reason
        assert r.startswith("auto:") and "busy" in r

    def test_exception(self):
        for bad in (0, -1, 1.5, True, "many"):
            with pytest.raises(ValueError, match="threads"):
                choose_threads(2, requested=bad)
        assert parse_threads("auto") is None and parse_threads(None) is None
        assert parse_threads(" 4 ") == 4


class TestLauncherShare:
    JOBLIB = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"

    def test_feature(self):
        assert launcher_share(None, 8) == (1, None)
        assert launcher_share({"_target_": "hydra._internal.core_plugins.basic_launcher."
                                           "BasicLauncher"}, 8) == (1, None)
        assert launcher_share({"_target_": self.JOBLIB, "n_jobs": 3}, 8) == (3, None)
        assert launcher_share({"_target_": self.JOBLIB, "n_jobs": -1}, 8) == (8, None)
        assert launcher_share({"_target_": self.JOBLIB, "n_jobs": -2}, 8) == (7, None)
        assert launcher_share({"_target_": self.JOBLIB}, 2) == (2, None)
        sub = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"
        assert launcher_share({"_target_": sub, "cpus_per_task": 2}, 16) == (1, 2)
        ray = "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher"
        assert launcher_share({"_target_": ray, "ray": {"remote": {"num_cpus": 4}}}, 16) == \
            (1, 4)

    def test_policy_for_a_joblib_sweep(self):
        jobs, per_job = launcher_share({"_target_": self.JOBLIB, "n_jobs": -1}, 2)
        assert choose_threads(2, 0.0, jobs, per_job).threads == 1


class TestMeasurement:
    def test_busy_between(self):
        a = CpuSample(busy=0, total=0, own=0.0, wall=0.0)
        # 2 cores over 1 s (200 jiffies): 190 busy; this process used 0.95 s of CPU
        b = CpuSample(busy=190, total=200, own=0.95, wall=1.0)
        assert busy_between(a, b, 2) == pytest.approx(0.95)
        # only this process: nobody else
        b = CpuSample(busy=200, total=200, own=2.0, wall=1.0)
        assert busy_between(a, b, 2) == pytest.approx(0.0)
        assert busy_between(a, a, 2) == 0.0

    def test_busy_cores_smoke(self):
        busy = threads.busy_cores(interval=0.05)
        assert 0.0 <= busy <= len(threads.available_cores())

    def test_apply(self, monkeypatch):
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        monkeypatch.setattr(threads, "busy_cores", lambda interval, cpus: 0.0)
        monkeypatch.setattr(threads, "available_cores", lambda: [0, 1, 2])
        c = apply_thread_policy("auto")
        assert c.threads == 3 and torch.get_num_threads() == 3
        monkeypatch.setattr(threads, "busy_cores", lambda interval, cpus: 2.0)
        assert apply_thread_policy("auto").threads == 1 and torch.get_num_threads() == 1
        monkeypatch.setenv("OMP_NUM_THREADS", "2")
        assert apply_thread_policy("auto").threads == 2
        assert apply_thread_policy(1).threads == 1

    def test_oversubscription_is_warned_about(self, monkeypatch, recwarn):
        """``threads=1000`` on 2 cores ran at 34 s per frame without a word."""
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        monkeypatch.setattr(threads, "available_cores", lambda: [0, 1])
        monkeypatch.setattr(torch, "set_num_threads", lambda n: None)  # not really 1000
        with pytest.warns(UserWarning, match=r"^threads=1000: more threads than the 2 cores "
                                             r".*use at most 2"):
            assert apply_thread_policy(1000).threads == 1000
        monkeypatch.setenv("OMP_NUM_THREADS", "8")
        with pytest.warns(UserWarning, match=r"^OMP_NUM_THREADS=8: more threads"):
            apply_thread_policy("auto")
        monkeypatch.delenv("OMP_NUM_THREADS")
        apply_thread_policy(2)
        assert not [w for w in recwarn if "more threads" in str(w.message)]


class TestGovernor:
    def test_feature(self, monkeypatch):
        """A load arriving mid-run drops the threads at the next check; leaving restores."""
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        monkeypatch.setattr(threads, "available_cores", lambda: [0, 1])
        samples = iter([
            CpuSample(0, 0, 0.0, 0.0),          # at construction
            CpuSample(100, 100, 1.0, 0.5),      # too soon: ignored
            CpuSample(400, 400, 4.0, 2.0),      # 2 s: 2 cores in use, both ours
            CpuSample(800, 800, 8.0, 4.0),      # the same
            CpuSample(1200, 1200, 10.0, 6.0),   # 2 cores in use, 1 ours: 1 busy elsewhere
            CpuSample(1400, 1600, 12.0, 8.0),   # 1 core in use, ours: idle again
        ])
        monkeypatch.setattr(threads, "cpu_sample", lambda cpus=None: next(samples))
        torch.set_num_threads(2)
        gov = ThreadGovernor("auto", interval=1.0)

        class S:
            frame = 0

        for f in range(1, 6):
            S.frame = f
            gov(S, {})
        assert [(f, n) for f, n, _ in gov.changes] == [(4, 1), (5, 2)]
        assert torch.get_num_threads() == 2
        s = gov.summary()
        assert [c["threads"] for c in s["changes"]] == [1, 2]

    def test_explicit_is_left_alone(self, monkeypatch):
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        gov = ThreadGovernor("auto", interval=0.0)
        gov(None, None)
        assert not gov.active and gov.changes == []
        monkeypatch.delenv("OMP_NUM_THREADS")
        assert not ThreadGovernor(2).active


def test_tracker_run_callbacks():
    """Tracker.run calls its callbacks after every frame (where the governor hooks in)."""
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data.synthetic.clips import synthesized_sequence

    seq = synthesized_sequence({"frames": 3}, "clean", {"image_size": [80, 60]}, seed=0)
    tr = build_tracker(tracker_config("g", ["tracker.num_particles=8",
                                            "tracker.inference.layers=1"]),
                       Runtime.from_sequence(seq))
    seen = []
    tr.run(seq, progress=False, callbacks=[lambda st, info: seen.append((st.frame,
                                                                         info.frame))])
    assert seen == [(1, 1), (2, 2)]
