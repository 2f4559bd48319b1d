"""torchmocap-synth: config composition, an in-process run, the console script and its errors."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module

from torchmocap.cli.synth import run
from torchmocap.data import Sequence

SMALL_SCENARIO = """\
name: tiny
rig: ring4
image_size: [80, 60]
silhouettes: {holes: 1.0}
imu: {noise: vmf, kappa: 500}
"""


def _compose(overrides: list[str]):
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="synth", overrides=overrides)


class TestSynthCli:
    def test_config_composes(self):
        cfg = _compose([])
        assert cfg.data.clip.path is None and cfg.data.clip.frames == "auto"
        assert cfg.data.clip.fps == 25 and cfg.data.clip.skip_frames == "auto"
        assert cfg.data.scenario == "studio" and cfg.seed == 0
        cfg = _compose(["data.scenario=outdoor", "seed=4", "data.clip.frames=10"])
        assert cfg.data.scenario == "outdoor" and cfg.seed == 4 and cfg.data.clip.frames == 10

    @pytest.mark.parametrize("override, match", [
        ("seed=1.5", r"^seed: expected an integer seed, got 1\.5"),
        ("seed=true", r"^seed: expected an integer seed"),
        ("preview_frame=2.5", r"^preview_frame: expected a frame index"),
        ("preview_frame=7", r"^preview_frame: 7 is outside the 3 frames"),
    ])
    def test_exception_seed_and_preview_frame(self, tmp_path, override, match):
        """``seed=1.5`` used to run seed 1; settings are checked, not coerced."""
        from torchmocap.data.synthetic.clips import DataConfigError

        scen = tmp_path / "tiny.yaml"
        scen.write_text(SMALL_SCENARIO)
        cfg = _compose([f"data.scenario={scen}", "data.clip.frames=3", override])
        with pytest.raises(DataConfigError, match=match):
            run(cfg, tmp_path / "out")

    def test_default_clip_is_bundled(self):
        from torchmocap.data.synthetic.clips import bundled_clip_path

        p = bundled_clip_path()
        assert p.name == "cmu_131_01_walk.bvh" and p.is_file()
        assert _compose([]).data._target_ == "torchmocap.data.synthetic.clips.synthesized_sequence"

    def test_run_in_process(self, tmp_path):
        scen = tmp_path / "tiny.yaml"
        scen.write_text(SMALL_SCENARIO)
        cfg = _compose([f"data.scenario={scen}", "data.clip.frames=3", "seed=2"])
        info = run(cfg, tmp_path / "out")
        seq = Sequence.load(tmp_path / "out" / "sequence")
        assert info["frames"] == 3 and seq.num_frames == 3 and seq.scenario == "tiny"
        assert seq.silhouettes.shape == (3, 4, 60, 80) and seq.meta.seed == 2
        assert seq.meta.clip["path"].endswith("cmu_131_01_walk.bvh")
        from PIL import Image

        with Image.open(tmp_path / "out" / "preview.png") as im:
            assert im.size == (5 * 80, 2 * 60)  # 4 views + depth, colour over mask

    def test_console_script(self, tmp_path, shared_data):
        exe = shutil.which("torchmocap-synth") or str(Path(sys.executable).parent /
                                                      "torchmocap-synth")
        # the console script is part of the package (pip install -e .): never a skip
        assert os.path.exists(exe), f"torchmocap-synth is not installed at {exe}"
        scen = tmp_path / "tiny.yaml"
        scen.write_text(SMALL_SCENARIO)
        env = dict(os.environ, OMP_NUM_THREADS="1")
        clip = shared_data / "mocap" / "cmu" / "01_01.bvh"
        r = subprocess.run([exe, f"data.clip.path={clip}", "data.clip.skip_frames=1",
                            "data.clip.frames=2", f"data.scenario={scen}",
                            f"hydra.run.dir={tmp_path / 'run'}"],
                           capture_output=True, text=True, env=env, timeout=300)
        assert r.returncode == 0, r.stderr
        info = json.loads(r.stdout.strip().splitlines()[-1])
        assert info["frames"] == 2
        man = json.loads((tmp_path / "run" / "sequence" / "manifest.json").read_text())
        assert man["meta"]["subject"]["family"] == "cmu_mb"
        assert (tmp_path / "run" / "preview.png").is_file()
        # unreadable clip: one line on stderr, exit status 2, nothing written
        bad = tmp_path / "bad.bvh"
        bad.write_text("this is not a BVH file\n")
        r = subprocess.run([exe, f"data.clip.path={bad}", f"hydra.run.dir={tmp_path / 'bad'}"],
                           capture_output=True, text=True, env=env, timeout=300)
        assert r.returncode == 2
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "bad.bvh" in lines[0] and "HIERARCHY" in lines[0]
        assert not (tmp_path / "bad" / "sequence").exists()
        r = subprocess.run([exe, "data.scenario=nowhere", f"hydra.run.dir={tmp_path / 'bad'}"],
                           capture_output=True, text=True, env=env, timeout=300)
        assert r.returncode == 2 and "nowhere" in r.stderr and len(r.stderr.splitlines()) == 1
