"""torchmocap-track batch_seeds=[...]: one run directory per seed with the outputs of the
separate run of that seed (same fingerprint, same track), shared sequences batched; settings
errors; the thread policy recorded in metrics.json."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from torchmocap.cli.batch import batch_seeds
from torchmocap.cli.track import run

SMALL = ["tracker=p", "data.clip.frames=4", "tracker.num_particles=16",
         "tracker.inference.layers=2",
         "+data.scenario_overrides.image_size=[80,60]", "overlays=0", "progress=false",
         "glb.enabled=false"]


def _compose(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", overrides=overrides)


@pytest.mark.parametrize("pinned", [False, True], ids=["seeded_data", "pinned_data"])
def test_batch_and_separate_runs(tmp_path, pinned):
    """Each seed of a batch gets a separate run's files; its track agrees with the separate
    run's on a short horizon (tracker P: no local descent to amplify the last bits of the
    batched energy); its fingerprint is the batch's own, so neither run is taken as the other's
    up-to-date result, while rerunning the batch skips."""
    extra = ["data.seed=0"] if pinned else []
    short = [*SMALL, "tracker=p", "data.clip.frames=3", *extra]
    out = tmp_path / "batch"
    out.mkdir()
    summary = run(_compose([*short, "batch_seeds=[0,2]"]), out)
    assert summary["batch_seeds"] == [0, 2]
    assert json.loads((out / "batch.json").read_text()) == json.loads(json.dumps(summary))
    sep = tmp_path / "seed2"
    sep.mkdir()
    alone = run(_compose([*short, "seed=2"]), sep)
    m = json.loads((out / "seed_2" / "metrics.json").read_text())
    assert m["seed"] == 2 and m["fingerprint"] != alone["fingerprint"]
    assert m["batch"] == {"seeds": [0, 2], "size": 2, "shared_sequence": pinned}
    a = np.load(out / "seed_2" / "track.npz")["theta"]
    b = np.load(sep / "track.npz")["theta"]
    assert a.shape == b.shape == (3, 31)
    np.testing.assert_allclose(a, b, atol=2e-3)
    assert np.abs(np.load(out / "seed_0" / "track.npz")["theta"][1:] - a[1:]).max() > 2e-2
    for f in ("tracked.bvh", "errors.png", "track.npz"):
        assert (out / "seed_0" / f).is_file()
    ov = yaml.safe_load((out / "seed_2" / ".hydra" / "overrides.yaml").read_text())
    assert "seed=2" in ov and not any(o.startswith("batch_seeds") for o in ov)
    # rerun: every seed up to date, nothing recomputed
    mtime = (out / "seed_0" / "track.npz").stat().st_mtime_ns
    run(_compose([*short, "batch_seeds=[0,2]"]), out)
    assert (out / "seed_0" / "track.npz").stat().st_mtime_ns == mtime
    # a separate run into a batch's seed directory recomputes (the batch's result is not its own)
    run(_compose([*short, "seed=0"]), out / "seed_0")
    assert (out / "seed_0" / "track.npz").stat().st_mtime_ns != mtime
    # another batch composition is another fingerprint
    again = run(_compose([*short, "batch_seeds=[0,1]"]), tmp_path / "other")
    m0 = json.loads((tmp_path / "other" / "seed_0" / "metrics.json").read_text())
    assert again["batch_seeds"] == [0, 1] and m0["fingerprint"] != m["fingerprint"]


def test_exception(tmp_path):
    for bad in ("[]", "[1,1]", "[0,1.5]", "3"):
        cfg = _compose([*SMALL, f"batch_seeds={bad}"])
        if bad == "[]":
            assert not cfg.batch_seeds  # empty: an ordinary run
            continue
        with pytest.raises(ValueError, match="batch_seeds"):
            batch_seeds(cfg)
    with pytest.raises(ValueError, match="checkpoint"):
        run(_compose([*SMALL, "batch_seeds=[0,1]", "checkpoint=state.pt"]), tmp_path)


def test_threads_recorded(tmp_path, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    m = run(_compose([*SMALL, "threads=auto"]), tmp_path)
    assert m["threads"]["threads"] == 1 and "OMP_NUM_THREADS" in m["threads"]["reason"]
    with pytest.raises(ValueError, match="threads"):
        run(_compose([*SMALL, "threads=zero"]), tmp_path / "x")
