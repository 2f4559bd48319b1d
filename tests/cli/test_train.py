"""torchmocap-train: a tiny run writes its outputs, resumes, and refuses a wrong checkpoint."""

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
    # a checkpoint of another architecture fails with the differing setting named
    with pytest.raises(ArchitectureMismatchError, match="hidden: file 8, config 4"):
        run(_cfg(tmp_path, ["epochs=2", "term.hidden=4",
                            f"resume={out / 'checkpoints' / 'last.pt'}"]), tmp_path / "bad")


def test_settings_errors_before_data(tmp_path):
    with pytest.raises(ValueError, match="objective.name"):
        run(_cfg(tmp_path, ["objective.name=magic"]), tmp_path / "x")
    assert not (tmp_path / "cache").exists()
