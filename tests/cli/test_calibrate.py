"""torchmocap-calibrate on the trimmed real recording: the refined calibration (read back by
the project's reader), its report and metrics.json in the run directory; a track that refines
first writes the same files beside it; bad settings fail naming the setting."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from torchmocap.cameras import read_calibration
from torchmocap.cli.calibrate import run

EXE = str(Path(sys.executable).parent / "torchmocap-calibrate")
pytestmark = pytest.mark.filterwarnings("ignore:.*codec's crop")


def _compose(name, overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


def test_feature_writes_refined_calibration(pose2sim_root, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    cfg = _compose("calibrate", [f"data.path={pose2sim_root}", "data.calibration.frames=[0,10]",
                                 "data.calibration.progress=false"])
    m = run(cfg, out)
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["frames"] == [0, 10] and saved["objective"] == "bundle"
    rig = read_calibration(out / "calibration" / "Calib_refined.toml")
    given = read_calibration(pose2sim_root / "calibration" / "Calib.toml")
    assert rig.names == given.names and rig.image_size.tolist() == given.image_size.tolist()
    moved = (rig.t.double() - given.t.double()).norm(dim=-1)
    assert bool((moved > 1e-4).all()) and bool((moved < 0.5).all())
    assert "| camera |" in (out / "calibration" / "refinement.md").read_text()
    assert "| camera |" in capsys.readouterr().out
    assert m["written"][0].endswith("Calib_refined.toml")


def test_exception_not_a_recording(tmp_path):
    r = subprocess.run([EXE, "data=default", f"hydra.run.dir={tmp_path / 'x'}"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 2
    assert "torchmocap-calibrate: error: data: torchmocap-calibrate refines a recording" in \
        r.stderr


def test_exception_unknown_group(pose2sim_root, tmp_path):
    r = subprocess.run([EXE, f"data.path={pose2sim_root}", "data.calibration.groups=[zoom]",
                        f"hydra.run.dir={tmp_path / 'x'}"], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 2 and "data.calibration.groups" in r.stderr and "'zoom'" in r.stderr
    assert not (tmp_path / "x" / "calibration").exists()


@pytest.mark.slow
def test_feature_track_refines_first(pose2sim_root, tmp_path):
    from torchmocap.cli.track import run as track

    out = tmp_path / "track"
    out.mkdir()
    cfg = _compose("track", ["data=recording", f"data.path={pose2sim_root}", "data.start=6",
                             "data.stop=10", "data.scale=0.25", "data.masks=none",
                             "data.calibration.refine=true", "data.calibration.frames=[0,6]",
                             "tracker=real_local", "evaluation.heldout_camera=cam02",
                             "overlays=0", "glb.enabled=false", "progress=false"])
    m = track(cfg, out)
    r = m["calibration_refinement"]
    assert r["frames"] == [0, 6] and len(r["report"]["cameras"]) == 4
    assert (out / "calibration" / "Calib_refined.toml").is_file()
    assert m["heldout"]["camera"] == "cam02"
