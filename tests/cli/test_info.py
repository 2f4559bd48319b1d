"""``torchmocap-info``: JSON description of motion and camera files; exit 2 on bad input."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from torchmocap.cli.info import describe, main


def _run(capsys, *argv) -> tuple[int, dict | None, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, (json.loads(out) if rc == 0 else None), err


@pytest.fixture(scope="module")
def mocap(shared_data: Path) -> Path:
    return shared_data / "mocap"


def test_bvh(capsys, mocap):
    rc, info, _ = _run(capsys, mocap / "cmu" / "131_01.bvh")
    assert rc == 0
    assert info["format"] == "bvh" and info["skeleton_family"] == "cmu_max"
    assert info["joints"] == 38 and len(info["joint_names"]) == 38
    assert info["frames"] == 994 and info["fps"] == 120.0
    assert info["duration_s"] == pytest.approx(994 / 120, abs=1e-3)
    assert abs(info["height_m"] - 1.42) < 0.03
    assert info["unmapped_joints"] == []


def test_amc_finds_its_asf(capsys, mocap):
    rc, info, _ = _run(capsys, mocap / "cmu" / "01_01.amc")
    assert rc == 0
    assert info["format"] == "amc" and info["skeleton_family"] == "cmu_asf"
    assert info["frames"] == 2751 and abs(info["height_m"] - 1.61) < 0.03


def test_amc_needs_asf_when_ambiguous(capsys, mocap):
    amc = mocap / "hdm05" / "HDM_bk_hopBothLegs1hops_017_120.amc"
    rc, _, err = _run(capsys, amc)
    assert rc == 2 and "3 .asf files beside this AMC" in err and "--asf" in err
    rc, info, _ = _run(capsys, amc, "--asf", mocap / "hdm05" / "HDM_bk.asf")
    assert rc == 0 and info["skeleton_family"] == "hdm05_asf"
    assert abs(info["height_m"] - 1.79) < 0.03


def test_asf_alone(capsys, mocap):
    rc, info, _ = _run(capsys, mocap / "hdm05" / "HDM_dg.asf")
    assert rc == 0 and info["format"] == "asf" and info["frames"] == 0
    assert abs(info["height_m"] - 1.68) < 0.03


def test_unknown_skeleton(capsys, tmp_path, mocap):
    text = (mocap / "cmu" / "cmu21_kick.bvh").read_text().replace("LeftLeg", "KneeL")
    (tmp_path / "odd.bvh").write_text(text)
    rc, info, err = _run(capsys, tmp_path / "odd.bvh")
    assert rc == 0
    assert err.startswith("torchmocap-info: warning: ") and "unknown length unit" in err
    assert info["skeleton_family"] is None and info["height_m"] is None
    assert info["unmapped_joints"] == ["l_knee"]


def test_bouguet_cal(capsys, shared_data):
    cal = shared_data / "multiview" / "bodytrack_sequenceB_1" / "CALIB" / "Camera1.cal"
    rc, info, _ = _run(capsys, cal)
    assert rc == 0 and info["format"] == "bouguet_cal"
    cam = info["cameras"][0]
    assert cam["focal_px"] == pytest.approx([584.242215, 583.310567])
    assert cam["image_size"] == [640, 480]
    import torch
    R, t = torch.tensor(cam["R"], dtype=torch.float64), torch.tensor(cam["t_m"],
                                                                      dtype=torch.float64)
    assert torch.allclose(torch.tensor(cam["center_m"], dtype=torch.float64), -(R.T @ t),
                          atol=1e-5)
    assert 1.5 < cam["center_m"][2] < 4  # a ceiling camera, metres (file is in mm)


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_camera_rig(capsys, tmp_path, suffix):
    from torchmocap.cameras import make_ring_rig, write_rig

    path = write_rig(make_ring_rig(num=3, radius=4.0, height=2.5), tmp_path / f"rig{suffix}")
    rc, info, _ = _run(capsys, path)
    assert rc == 0 and info["format"] == f"camera_rig_{suffix[1:]}"
    assert len(info["cameras"]) == 3
    for cam in info["cameras"]:
        x, y, z = cam["center_m"]
        assert (x * x + y * y) ** 0.5 == pytest.approx(4.0, abs=1e-4)
        assert z == pytest.approx(2.5, abs=1e-4)


@pytest.mark.parametrize("name, text, expect", [
    ("bad.bvh", "HIERARCHY\nROOT a\n{\n OFFSET 0 0 0\n CHANNELS 1 Wrotation\n}\n",
     "bad.bvh:5: unknown channel 'Wrotation'"),
    ("bad.amc", "1\nroot 0 0 0 0 0 0\n", ".asf"),
    ("notes.txt", "hello", "unsupported file type '.txt'"),
    ("bad.cal", "1\n2\n", "bad.cal"),
])
def test_bad_input_exit_2(capsys, tmp_path, name, text, expect):
    (tmp_path / name).write_text(text)
    rc, _, err = _run(capsys, tmp_path / name)
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith("torchmocap-info: error: ")
    assert expect in err and "Traceback" not in err


def test_missing_file(capsys, tmp_path):
    rc, _, err = _run(capsys, tmp_path / "nope.bvh")
    assert rc == 2 and "no such file" in err


def test_describe_bundled_clip():
    from torchmocap.io import bundled_clip_path

    info = describe(bundled_clip_path())
    assert info["skeleton_family"] == "cmu_max" and info["frames"] == 480


def test_console_script(tmp_path):
    from torchmocap.io import bundled_clip_path

    exe = shutil.which("torchmocap-info") or str(Path(sys.executable).parent / "torchmocap-info")
    if not Path(exe).exists():
        pytest.skip("torchmocap-info console script not installed (pip install -e .)")
    ok = subprocess.run([exe, str(bundled_clip_path())], capture_output=True, text=True,
                        timeout=120)
    assert ok.returncode == 0 and json.loads(ok.stdout)["duration_s"] == 4.0
    bad = subprocess.run([exe, str(tmp_path / "missing.bvh")], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().count("\n") == 0
