"""Every file of shared/data/mocap (its trimmed copy in tests/data_files) loads with its family
and the subject size the data README lists."""

from __future__ import annotations

import pytest
import torch

from torchmocap.io import chain_height, human31_positions, load_motion, unmapped_joints

# (file, family, README chain length in metres); tolerance +-3 cm
BVH = [
    ("01_01.bvh", "cmu_mb", 1.49),
    ("131_01.bvh", "cmu_max", 1.42),
    ("131_02.bvh", "cmu_max", 1.42),
    ("60_12_scaled.bvh", "daz43", 1.23),
    *[(f"cmu21_{n}.bvh", "cmu21", h) for n, h in [
        ("box-1", 1.41), ("dance", 1.415), ("female-walk", 1.415), ("hop", 1.415),
        ("jump-across", 1.415), ("jumping-jack", 1.415), ("kick", 1.415), ("swim", 1.415)]],
]
HDM = [
    "HDM_bd_jogLeftCircle4StepsRstart_001_120.amc",
    "HDM_bd_kickLFront1Reps_001_120.amc",
    "HDM_bd_rotateArmsBothBackward1Reps_001_120.amc",
    "HDM_bd_sneak2StepsLStart_001_120.amc",
    "HDM_bd_throwBasketball_001_120.amc",
    "HDM_bk_elbowToKnee1RepsLelbowStart_007_120.amc",
    "HDM_bk_hopBothLegs1hops_017_120.amc",
    "HDM_dg_grabHighR_011_120.amc",
    "HDM_dg_squat1Reps_025_120.amc",
]


def _check_plausible(clip):
    """Root translation and bone offsets in one unit: feet reach the floor, head stays above."""
    p = human31_positions(clip)  # (T, 21, 3) in HUMAN31_JOINTS order
    feet = p[:, [15, 16, 19, 20], 2].amin(-1)  # ankles and toes
    assert -0.12 < float(feet.median()) < 0.2
    assert float((p[:, 4, 2] - feet).median()) > 1.0  # head top well above the feet
    assert torch.isfinite(p).all()


@pytest.mark.parametrize("name, family, height", BVH, ids=[b[0] for b in BVH])
def test_bvh_family_and_height(cmu, name, family, height):
    clip = load_motion(cmu / name)
    assert clip.skeleton_family == family
    assert unmapped_joints(clip) == []
    h = chain_height(clip)
    if family == "cmu21":
        assert 1.39 - 0.03 <= h <= 1.44 + 0.03
    assert abs(h - height) <= 0.03, h
    _check_plausible(clip)


def test_cmu_asf_height(cmu):
    clip = load_motion(cmu / "01_01.amc")  # the only .asf beside it
    assert clip.skeleton_family == "cmu_asf"
    assert abs(chain_height(clip) - 1.61) <= 0.03
    assert abs(chain_height(load_motion(cmu / "01.asf")) - 1.61) <= 0.03
    _check_plausible(clip)


@pytest.mark.parametrize("name", HDM)
def test_hdm05_family_and_height(hdm05, name):
    clip = load_motion(hdm05 / name, asf=hdm05 / f"{name[:6]}.asf")
    assert clip.skeleton_family == "hdm05_asf"
    assert unmapped_joints(clip) == []
    h = chain_height(clip)
    assert 1.61 - 0.03 <= h <= 1.79 + 0.03
    expected = {"bd": 1.61, "bk": 1.79, "dg": 1.68}[name[4:6]]
    assert abs(h - expected) <= 0.03
    _check_plausible(clip)


def test_every_file_is_covered(shared_data):
    files = {p.name for p in (shared_data / "mocap").rglob("*") if p.suffix in (".bvh", ".amc")}
    covered = {b[0] for b in BVH} | set(HDM) | {"01_01.amc"}
    assert files == covered
