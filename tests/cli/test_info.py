"""``torchmocap-info``: JSON description of motion and camera files; exit 2 on bad input."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from torchmocap.cli.info import describe, main


def _strict(text: str):
    """json.loads that refuses NaN/Infinity (Python's json accepts them; JSON does not)."""
    def bad(name):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=bad)


def _run(capsys, *argv) -> tuple[int, dict | None, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, (_strict(out) if rc == 0 else None), err


@pytest.fixture(scope="module")
def mocap(shared_data: Path) -> Path:
    return shared_data / "mocap"


def test_bvh(capsys, mocap):
    rc, info, _ = _run(capsys, mocap / "cmu" / "131_01.bvh")
    assert rc == 0
    assert info["format"] == "bvh" and info["skeleton_family"] == "cmu_max"
    assert info["joints"] == 38 and len(info["joint_names"]) == 38
    assert info["frames"] == 120 and info["fps"] == 120.0  # trimmed copy (994 in all)
    assert info["duration_s"] == pytest.approx(120 / 120, abs=1e-3)
    assert abs(info["height_m"] - 1.42) < 0.03
    assert info["unmapped_joints"] == [] and info["guessed_joints"] == []
    assert info["joint_map_source"] == "skeleton_map"
    assert info["joint_map"]["l_knee"] == "LeftKnee" and info["ambiguous_joints"] == {}
    assert info["reference_frames"] == 0


def test_reference_frame_reported(capsys, mocap):
    """The cgspeed MotionBuilder BVH's synthetic T-pose frame 0 is reported (tracking drops it
    with skip_frames=auto); the file itself is described whole."""
    rc, info, _ = _run(capsys, mocap / "cmu" / "01_01.bvh")
    assert rc == 0 and info["skeleton_family"] == "cmu_mb"
    assert info["reference_frames"] == 1


def test_amc_finds_its_asf(capsys, mocap):
    rc, info, _ = _run(capsys, mocap / "cmu" / "01_01.amc")
    assert rc == 0
    assert info["format"] == "amc" and info["skeleton_family"] == "cmu_asf"
    assert info["frames"] == 120 and abs(info["height_m"] - 1.61) < 0.03


def test_amc_finds_its_asf_by_name(capsys, mocap):
    # three .asf files beside it: the one named after the AMC (HDM05's convention)
    amc = mocap / "hdm05" / "HDM_bk_hopBothLegs1hops_017_120.amc"
    rc, info, _ = _run(capsys, amc)
    assert rc == 0 and info["skeleton_family"] == "hdm05_asf"
    assert abs(info["height_m"] - 1.79) < 0.03  # bk's skeleton, not bd's or dg's
    rc, other, _ = _run(capsys, amc, "--asf", mocap / "hdm05" / "HDM_dg.asf")
    assert rc == 0 and abs(other["height_m"] - info["height_m"]) > 0.05  # --asf wins


def test_amc_needs_asf_when_ambiguous(capsys, tmp_path, mocap):
    for name in ("HDM_bk.asf", "HDM_dg.asf"):
        shutil.copy(mocap / "hdm05" / name, tmp_path / name)
    amc = tmp_path / "hop.amc"  # named after neither
    shutil.copy(mocap / "hdm05" / "HDM_bk_hopBothLegs1hops_017_120.amc", amc)
    rc, _, err = _run(capsys, amc)
    assert rc == 2 and "2 .asf files beside this AMC and none named after it" in err
    assert "HDM_bk.asf, HDM_dg.asf" in err and "--asf" in err
    rc, info, _ = _run(capsys, amc, "--asf", tmp_path / "HDM_bk.asf")
    assert rc == 0 and info["skeleton_family"] == "hdm05_asf"
    assert abs(info["height_m"] - 1.79) < 0.03


def test_asf_alone(capsys, mocap):
    rc, info, _ = _run(capsys, mocap / "hdm05" / "HDM_dg.asf")
    assert rc == 0 and info["format"] == "asf" and info["frames"] == 0
    assert abs(info["height_m"] - 1.68) < 0.03


def test_unknown_skeleton(capsys, tmp_path, mocap):
    text = (mocap / "cmu" / "cmu21_kick.bvh").read_text().replace("LeftLeg", "Gelenk7")
    (tmp_path / "odd.bvh").write_text(text)
    rc, info, err = _run(capsys, tmp_path / "odd.bvh")
    assert rc == 0
    assert err.startswith("torchmocap-info: warning: ") and "unknown length unit" in err
    assert info["skeleton_family"] is None and info["height_m"] is None
    assert info["unmapped_joints"] == ["l_knee"] and info["joint_map"]["l_knee"] is None
    assert info["joint_map_source"] == "guessed" and "l_knee" not in info["guessed_joints"]
    assert info["joint_map"]["r_knee"] == "RightLeg"


def test_unseen_family_guessed(capsys, shared_data):
    """A 22-joint skeleton of no known family (UpperArm_L, LowerLeg_R, Toes_L, zero-length end
    sites): every joint is mapped by its name, and the output says they were guessed."""
    bvh = shared_data / "synthetic" / "unseen22_suffix_L.bvh"
    rc, info, err = _run(capsys, bvh)
    # no map gives the unit: inferred from the ankle-head chain (159.8 file units: cm)
    assert rc == 0 and "inferred 0.01 m per unit (cm)" in err and "159.8 units" in err
    assert info["unit_m"] == 0.01
    assert info["skeleton_family"] is None and info["joints"] == 27
    assert info["joint_map_source"] == "guessed" and info["unmapped_joints"] == []
    assert info["guessed_joints"] == list(info["joint_map"]) and len(info["joint_map"]) == 21
    assert info["joint_map"]["l_shoulder"] == "UpperArm_L"
    assert info["joint_map"]["r_knee"] == "LowerLeg_R" and info["joint_map"]["l_toe"] == "Toes_L"
    # ankle-hip-head chain (the head's end site has zero length)
    assert info["height_m"] == pytest.approx(1.598, abs=0.001)


def test_skeleton_map_option(capsys, tmp_path, mocap, shared_data):
    from torchmocap.io import HUMAN31_JOINTS

    # a map YAML for the unseen family: the output follows it and guesses nothing
    bvh = shared_data / "synthetic" / "unseen22_suffix_L.bvh"
    rc, guessed, _ = _run(capsys, bvh)
    lines = ["family: unseen22_test", "format: bvh", "unit: 0.01", "joints:"]
    lines += [f"  {h}: {v}" for h, v in guessed["joint_map"].items()]
    yml = tmp_path / "unseen22.yaml"
    yml.write_text("\n".join(lines) + "\n")
    rc, info, err = _run(capsys, bvh, "--skeleton-map", yml)
    assert rc == 0 and "unknown length unit" not in err
    assert info["skeleton_family"] == "unseen22_test" and info["unit_m"] == 0.01
    assert info["joint_map_source"] == "skeleton_map" and info["guessed_joints"] == []
    assert info["joint_map"] == guessed["joint_map"]
    assert info["height_m"] == pytest.approx(1.598, abs=0.001)
    # a built-in family by name, on a file of another family: what it cannot map is listed
    rc, info, _ = _run(capsys, mocap / "cmu" / "131_01.bvh", "--skeleton-map", "cmu21")
    assert rc == 0 and info["skeleton_family"] == "cmu21"
    assert info["joint_map_source"] == "skeleton_map" and "l_knee" in info["unmapped_joints"]
    assert set(info["joint_map"]) == set(HUMAN31_JOINTS)
    rc, _, err = _run(capsys, mocap / "cmu" / "131_01.bvh", "--skeleton-map", "no_such_map")
    assert rc == 2 and "unknown skeleton map 'no_such_map'" in err
    cal = shared_data / "multiview" / "bodytrack_sequenceB_1" / "CALIB" / "Camera1.cal"
    rc, _, err = _run(capsys, cal, "--skeleton-map", "cmu21")
    assert rc == 2 and "--skeleton-map: applies to motion files" in err


def test_absurd_frame_time_exit_2(capsys, tmp_path, mocap):
    """``Frame Time: 1e300`` was reported as fps 0.0; now the file and line are named."""
    text = (mocap / "cmu" / "cmu21_kick.bvh").read_text()
    lines = text.splitlines()
    ln = next(i for i, s in enumerate(lines) if s.startswith("Frame Time")) + 1
    lines[ln - 1] = "Frame Time: 1e300"
    (tmp_path / "slow.bvh").write_text("\n".join(lines) + "\n")
    rc, _, err = _run(capsys, tmp_path / "slow.bvh")
    assert rc == 2 and f"slow.bvh:{ln}: frame time 1e300 s is not a plausible frame time" in err


def test_output_is_strict_json(capsys, tmp_path, shared_data):
    """Lengths that overflow (a chain height of inf) are an error, never ``Infinity``."""
    text = (shared_data / "synthetic" / "unseen22_suffix_L.bvh").read_text()
    text = text.replace("OFFSET 0 -41.999999 0", "OFFSET 0 -1e308 0")  # thighs and shanks
    assert text.count("1e308") == 4
    (tmp_path / "huge.bvh").write_text(text)
    rc, info, err = _run(capsys, tmp_path / "huge.bvh")
    assert rc == 2 and info is None
    assert "height_m is inf (not a finite number)" in err and "Infinity" not in err
    from torchmocap.cli.info import to_json

    with pytest.raises(ValueError, match=r"cameras\[0\]\.focal_px\[1\] is nan"):
        to_json({"path": "x", "cameras": [{"focal_px": [1.0, float("nan")]}]})
    assert _strict(to_json({"path": "x", "a": [1.5, None]})) == {"path": "x", "a": [1.5, None]}


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
    # the console script is part of the package (pip install -e .): never a skip
    assert Path(exe).exists(), f"torchmocap-info is not installed at {exe}"
    ok = subprocess.run([exe, str(bundled_clip_path())], capture_output=True, text=True,
                        timeout=120)
    assert ok.returncode == 0 and json.loads(ok.stdout)["duration_s"] == 4.0
    bad = subprocess.run([exe, str(tmp_path / "missing.bvh")], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().count("\n") == 0
