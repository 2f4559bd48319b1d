"""Assembly: runtime dependencies by name, every option of every config group builds, a user's
own components enter through YAML alone, and errors name the config path."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from torchmocap.assembly import ComponentError, Runtime, build, build_tracker, tracker_config
from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.ik import PAPER_SENSORS, SensorManifold
from torchmocap.skeleton import human31

CONF = Path(__file__).resolve().parents[1] / "torchmocap" / "conf"
PLUGINS = Path(__file__).resolve().parent / "plugins"
EXE = str(Path(sys.executable).parent / "torchmocap-track")
COMPONENT_GROUPS = ["predictor", "proposal", "noise", "likelihood", "term", "inference",
                    "estimator", "resampler", "diffusion"]


@pytest.fixture(scope="module")
def runtime():
    sk = human31()
    return Runtime(skeleton=sk, body=CapsuleBody(sk), rig=make_ring_rig(4).float(),
                   manifold=SensorManifold(sk, PAPER_SENSORS), sensors=dict(PAPER_SENSORS))


def _compose(overrides, searchpath=None):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        extra = [f"hydra.searchpath=[file://{searchpath}]"] if searchpath else []
        return compose(config_name="track", overrides=[*extra, *overrides])


def _options(group):
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("group,option", [(g, o) for g in COMPONENT_GROUPS for o in
                                          _options(g)])
def test_every_option_of_every_component_group_builds(runtime, group, option):
    cfg = _compose([f"+{group}@probe={option}"])
    assert "_target_" in cfg.probe, (group, option)
    obj = build(cfg.probe, runtime, _path="probe")
    assert obj is not None


@pytest.mark.parametrize("option", _options("tracker"))
def test_every_tracker_preset_builds(runtime, option):
    from torchmocap.filters import Tracker

    tr = build_tracker(tracker_config(option), runtime, seed=3)
    assert isinstance(tr, Tracker) and tr.name == option and tr.seed == 3
    assert tr.requires  # every preset reads something


def test_every_data_option_composes_and_the_default_builds(tmp_path):
    assert _options("data") == ["bodytrack", "default", "recording"]
    assert _options("data/clip") == ["bundled"]
    from torchmocap.assembly import load_sequence

    cfg = _compose(["data.clip.frames=2", "data.scenario=clean", "seed=1",
                    "+data.scenario_overrides.image_size=[80,60]"])
    seq = load_sequence(cfg)
    assert seq.num_frames == 2 and seq.silhouettes.shape[-2:] == (60, 80)
    assert seq.meta.seed == 1 and seq.meta.clip["start"] == 0.0
    bt = _compose(["data=bodytrack"]).data
    assert bt._target_.endswith("load_bodytrack_sequence") and bt.headings == 12


def test_runtime_dependencies_are_passed_by_name(runtime):
    from torchmocap.likelihoods import SilhouetteLikelihood

    t = build({"_target_": "torchmocap.likelihoods.SilhouetteLikelihood", "fg_samples": 10},
              runtime)
    assert isinstance(t, SilhouetteLikelihood) and t.body is runtime.body and t.rig is runtime.rig
    # a value set in the config wins over the runtime's
    other = make_ring_rig(2)
    t2 = build({"_target_": "torchmocap.likelihoods.SilhouetteLikelihood", "rig": other},
               runtime)
    assert t2.rig is not runtime.rig
    # nested: the rejection proposal's criterion and base both get the runtime's pieces
    p = build(OmegaConf.to_container(tracker_config("rs").proposal), runtime)
    assert p.error_fn.manifold is runtime.manifold
    assert torch.equal(p.base.lower, runtime.skeleton.lower.float())


def test_errors_name_the_config_path(runtime):
    no_imu = Runtime(skeleton=runtime.skeleton, body=runtime.body, rig=runtime.rig)
    with pytest.raises(ComponentError, match=r"tracker.proposal: .*needs tracking IMUs"):
        build_tracker(tracker_config("p"), no_imu)
    with pytest.raises(ComponentError, match=r"probe.noise: cannot import _target_ 'nope.X'"):
        build({"_target_": "torchmocap.proposals.ManifoldProposal",
               "noise": {"_target_": "nope.X"}}, runtime, _path="probe")
    with pytest.raises(ComponentError, match=r"tracker.proposal.noise: kappa: expected"):
        build_tracker(tracker_config("p", ["tracker.proposal.noise.kappa=-1"]), runtime)
    with pytest.raises(ComponentError, match=r"tracker.likelihood: weights.silhouette: expected"):
        build_tracker(tracker_config("g", ["tracker.likelihood.weights.silhouette=nan"]),
                      runtime)
    with pytest.raises(ComponentError, match="unexpected keyword argument 'kapa'"):
        build_tracker(tracker_config("p", ["+tracker.proposal.noise.kapa=3"]), runtime)
    with pytest.raises(ComponentError, match="expected a config with a _target_"):
        build({"x": 1}, runtime)
    with pytest.raises(ComponentError, match="expected a torchmocap.filters.Tracker"):
        build_tracker({"_target_": "builtins.dict"}, runtime)
    for bad in (1.5, True, "3"):  # int() would run 1.5 as seed 1
        with pytest.raises(ValueError, match="seed: expected an integer"):
            build_tracker(tracker_config("p"), runtime, seed=bad)


def test_a_user_component_enters_through_yaml_alone(runtime, monkeypatch):
    monkeypatch.syspath_prepend(str(PLUGINS))
    cfg = _compose(["tracker=g", "+term@tracker.likelihood.terms.upright=upright",
                    "+tracker.likelihood.weights.upright=0.5", "proposal@tracker.proposal="
                    "half_step"], searchpath=PLUGINS / "conf")
    tr = build_tracker(cfg.tracker, runtime)
    up = tr.likelihood.terms["upright"]
    assert type(up).__name__ == "UprightLikelihood" and type(up).__module__ == "user_components"
    assert tr.likelihood.weights["upright"] == 0.5
    assert type(tr.proposal).__name__ == "HalfStepProposal"
    # it is evaluated inside the tracker's energy
    from torchmocap.data import Frame
    from torchmocap.likelihoods import FrameEnergy

    sk = runtime.skeleton
    masks = torch.zeros(4, 240, 320, dtype=torch.bool)
    masks[:, 100:140, 150:170] = True
    frame = Frame(index=0, time=0.0, silhouettes=masks,
                  images=torch.zeros(4, 240, 320, 3, dtype=torch.uint8))
    V = FrameEnergy(tr.likelihood, tr.likelihood.prepare(frame), sk)
    th = sk.zero_pose((3,))
    th[1, sk.dof_index("spine_flex")] = 0.5
    terms = V.terms(th)
    assert terms["upright"][0].item() == pytest.approx(0.0, abs=1e-6)
    assert terms["upright"][1].item() > 0.2


@pytest.mark.slow
def test_a_user_component_runs_from_the_command_line(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(PLUGINS))
    run_dir = tmp_path / "run"
    r = subprocess.run([EXE, f"hydra.searchpath=[file://{PLUGINS / 'conf'}]", "tracker=g",
                        "+term@tracker.likelihood.terms.upright=upright",
                        "+tracker.likelihood.weights.upright=0.5", "data.clip.frames=3",
                        "tracker.num_particles=20", "tracker.inference.layers=2",
                        "+data.scenario_overrides.image_size=[80,60]", "overlays=0",
                        "progress=false", f"hydra.run.dir={run_dir}"],
                       capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((run_dir / "metrics.json").read_text())
    assert set(m["energy_mean"]) == {"silhouette", "appearance", "upright"}
