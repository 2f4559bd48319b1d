"""torchmocap-train: a tiny run writes its outputs, resumes, and refuses a wrong checkpoint;
settings errors name the setting before any synthesis; the default config trains on bundled
data from any directory."""

from __future__ import annotations

import csv

import pytest
from hydra import compose, initialize_config_module

from torchmocap.cli.train import run
from torchmocap.likelihoods import ArchitectureMismatchError
from torchmocap.likelihoods.learned import read_weights

TINY = [
    "data.train_clips=[{name: w, path: null, frames: 5}]",
    "data.val_clips=[{name: v, path: null, start: 1.5, frames: 4}]",
    "data.negatives.num_particles=12", "data.negatives.proposal_negatives=4",
    "data.negatives.hard_negatives=2", "batch_size=2", "progress=false",
]


def _cfg(tmp_path, extra=()):
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="train", overrides=[
            *TINY, f"data.cache_dir={tmp_path / 'cache'}", *extra])


def test_train_resume_and_mismatch(tmp_path):
    out = tmp_path / "run"
    s = run(_cfg(tmp_path, ["epochs=1", f"export={tmp_path / 'exported.pt'}"]), out)
    assert s["epochs"] == 1 and s["train_frames"] == 2
    for f in ("metrics.csv", "summary.json", "weights.pt", "checkpoints/last.pt",
              "checkpoints/best.pt"):
        assert (out / f).is_file(), f
    assert any((out / "tb").iterdir())
    assert read_weights(tmp_path / "exported.pt")["term"] == "LearnedFeatureLikelihood"
    # resume for one more epoch: the metrics continue
    out2 = tmp_path / "resumed"
    s2 = run(_cfg(tmp_path, ["epochs=2", f"resume={out / 'checkpoints' / 'last.pt'}"]), out2)
    assert s2["epochs"] == 2
    rows = list(csv.DictReader(open(out2 / "metrics.csv")))
    assert [r["epoch"] for r in rows] == ["0", "1", "2"]
    # a checkpoint that has trained the epochs asked for already: named (it failed on a
    # missing checkpoints/last.pt before)
    with pytest.raises(ValueError, match=r"^epochs: the checkpoint .*last\.pt has trained 1 "
                                         r"epochs already; set epochs > 1"):
        run(_cfg(tmp_path, ["epochs=1", f"resume={out / 'checkpoints' / 'last.pt'}"]),
            tmp_path / "done")
    # a checkpoint of another architecture fails with the differing setting named
    with pytest.raises(ArchitectureMismatchError, match="hidden: file 8, config 4"):
        run(_cfg(tmp_path, ["epochs=2", "term.hidden=4",
                            f"resume={out / 'checkpoints' / 'last.pt'}"]), tmp_path / "bad")


def test_settings_errors_before_data(tmp_path):
    with pytest.raises(ValueError, match="objective.name"):
        run(_cfg(tmp_path, ["objective.name=magic"]), tmp_path / "x")
    assert not (tmp_path / "cache").exists()


@pytest.mark.parametrize("overrides, message", [
    (["data.train_clips=[]"], r"^data\.train_clips: expected a list of at least one clip"),
    (["epochs=0"], r"^epochs: expected a positive int, got 0"),
    (["seed=18446744073709551616"], r"^seed: expected an integer in"),
    (["term=silhouette"], r"^term: torchmocap\.likelihoods\.SilhouetteLikelihood is not a "
                          r"learned likelihood term .* trains term=learned_features \| "
                          r"learned_render"),
])
def test_settings_errors_name_the_setting(tmp_path, overrides, message):
    """``data.train_clips=[]`` failed with 'list index out of range', ``epochs=0`` on a missing
    checkpoints/last.pt after the synthesis, a term that is not learned with the constructor's
    'unexpected keyword argument weights' after it."""
    with pytest.raises(ValueError, match=message):
        run(_cfg(tmp_path, overrides), tmp_path / "x")
    assert not (tmp_path / "cache").exists()


def test_default_clips_are_bundled():
    """The default config pointed into ../shared/data (only there from the repository root);
    its clips are the packaged walk now (``training_set=mocap`` has the real ones)."""
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        cfg = compose(config_name="train")
        mocap = compose(config_name="train", overrides=["training_set=mocap"])
    clips = [*cfg.data.train_clips, *cfg.data.val_clips]
    assert clips and all(c.path is None for c in clips)
    assert len(mocap.data.train_clips) == 8 and len(mocap.data.val_clips) == 2


@pytest.mark.slow
def test_console_default_config_runs_outside_the_repository(tmp_path):
    """The documented default, from a directory that is not the repository: trains (one epoch
    here) and writes its weights; failures keep the contract (failure.json, one line, exit 2)."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    exe = str(Path(sys.executable).parent / "torchmocap-train")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([exe, "epochs=1", "progress=false", "tensorboard=false",
                        f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True,
                       cwd=tmp_path, env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["epochs"] == 1 and summary["train_frames"] > 20
    assert (tmp_path / "run" / "weights.pt").is_file()
    r = subprocess.run([exe, "data.train_clips=[]", f"hydra.run.dir={tmp_path / 'bad'}"],
                       capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "data.train_clips" in r.stderr and (tmp_path / "bad" / "failure.json").is_file()
