"""Skeleton maps: built-in YAMLs, detection, user maps, and the error for unknown skeletons."""

from __future__ import annotations

import pytest
import torch

from torchmocap.io import (
    HUMAN31_JOINTS,
    MotionClip,
    SkeletonMapError,
    chain_height,
    detect_family,
    guess_joint_map,
    human31_positions,
    known_families,
    load_skeleton_map,
    map_joints,
    read_bvh,
    unmapped_joints,
    write_bvh,
)
from torchmocap.skeleton import human31

FAMILIES = ["cmu21", "cmu_asf", "cmu_max", "cmu_mb", "daz43", "hdm05_asf", "human31"]


def test_human31_names_match_core_preset():
    assert list(HUMAN31_JOINTS) == human31().joint_names


@pytest.mark.parametrize("family", FAMILIES)
def test_builtin_maps_are_complete(family):
    assert family in known_families()
    m = load_skeleton_map(family)
    assert m.family == family
    assert set(m.joints) == set(HUMAN31_JOINTS)  # every human31 joint has a source joint
    assert set(m.bones) <= set(HUMAN31_JOINTS) and m.bones
    assert m.detect
    if m.source_format == "bvh":
        assert m.unit is not None and m.unit > 0  # BVH files do not state their unit


def test_units_per_family():
    inch_045 = 0.0254 / 0.45
    assert load_skeleton_map("cmu_mb").unit == pytest.approx(inch_045)
    assert load_skeleton_map("cmu_max").unit == pytest.approx(inch_045)
    assert load_skeleton_map("cmu21").unit == 0.01
    assert load_skeleton_map("daz43").unit == 1.0
    assert load_skeleton_map("cmu_asf").unit is None  # the ASF states it


def test_detect_family_specificity():
    mb = load_skeleton_map("cmu_mb")
    cmu21 = load_skeleton_map("cmu21")
    assert set(cmu21.detect) <= set(mb.detect)  # CMU21 names are a subset of the MB names ...
    assert detect_family(list(mb.detect), source_format="bvh") == "cmu_mb"  # ... MB still wins
    assert detect_family(list(cmu21.detect), source_format="bvh") == "cmu21"
    asf_names = list(load_skeleton_map("cmu_asf").detect)
    assert detect_family(asf_names, "asf", "x/01.asf") == "cmu_asf"
    assert detect_family(asf_names, "asf", "x/HDM_bd.asf") == "hdm05_asf"
    assert detect_family(asf_names, "bvh") is None  # format mismatch
    assert detect_family(["a", "b"]) is None


@pytest.fixture(scope="module")
def walk(cmu):
    return read_bvh(cmu / "131_01.bvh").slice(0, 20)


def test_map_joints_and_positions(walk):
    idx = map_joints(walk)
    assert walk.joint_names[idx["l_knee"]] == "LeftKnee"
    assert walk.joint_names[idx["head_top"]] == "Head_end"
    p = human31_positions(walk)
    assert p.shape == (20, 21, 3)
    assert torch.equal(p[:, HUMAN31_JOINTS.index("l_elbow")],
                       walk.global_positions()[:, walk.joint_index("LeftElbow")])


def _renamed(clip: MotionClip, rename: dict[str, str]) -> MotionClip:
    names = [rename.get(n, n) for n in clip.joint_names]
    return MotionClip(**{**clip.__dict__, "joint_names": names, "skeleton_family": None,
                         "local_translations": {}})


def test_unknown_skeleton_error_lists_joints_and_suggestions(walk):
    odd = _renamed(walk, {"LeftKnee": "L_Knee_jnt", "Head_end": "HeadTop_tip",
                          "LeftToe": "lToe_j", "Hips": "Hips"})
    assert detect_family(odd) is None
    assert unmapped_joints(odd) == ["head_top", "l_knee", "l_toe"]
    with pytest.raises(SkeletonMapError) as e:
        map_joints(odd)
    msg = str(e.value)
    assert "cannot map 3 human31 joint(s): ['head_top', 'l_knee', 'l_toe']" in msg
    assert "l_knee: closest source joints ['L_Knee_jnt'" in msg
    assert "head_top: closest source joints ['HeadTop_tip'" in msg
    assert "l_toe: closest source joints ['lToe_j'" in msg and "docs/skeleton_maps.md" in msg
    assert "RightKnee" not in msg.split("l_knee:")[1].split("\n")[0]  # wrong side not offered
    with pytest.raises(SkeletonMapError):
        chain_height(odd)
    # guessing works where names are known spellings
    assert guess_joint_map(odd)["r_knee"] == "RightKnee"


def test_user_map_yaml(walk, tmp_path, monkeypatch):
    from torchmocap.io import skeleton_maps

    monkeypatch.setattr(skeleton_maps, "_USER_MAPS", {})
    odd = _renamed(walk, {"LeftKnee": "L_Knee_jnt", "Head_end": "HeadTop_tip",
                          "LeftToe": "lToe_j"})
    joints = dict(load_skeleton_map("cmu_max").joints)
    joints.update(l_knee="L_Knee_jnt", head_top="HeadTop_tip", l_toe="lToe_j")
    lines = ["family: my_rig", "format: bvh", "unit: 0.0564444",
             "detect: [L_Knee_jnt, HeadTop_tip]", "joints:"]
    lines += [f"  {k}: {v}" for k, v in joints.items()]
    path = tmp_path / "my_rig.yaml"
    path.write_text("\n".join(lines) + "\n")
    m = load_skeleton_map(path)
    assert m.family == "my_rig" and m.unit == 0.0564444
    assert detect_family(odd, maps=[path]) == "my_rig"
    assert unmapped_joints(odd, path) == []
    assert chain_height(odd, path) == pytest.approx(chain_height(walk))
    # a BVH read with the map takes its unit and family; the family name resolves afterwards
    bvh = write_bvh(tmp_path / "odd.bvh", odd, unit=0.0564444)
    clip = read_bvh(bvh, skeleton_map=path)
    assert clip.skeleton_family == "my_rig" and clip.unit == 0.0564444
    assert chain_height(clip) == pytest.approx(chain_height(walk), abs=1e-6)
    assert detect_family(read_bvh(bvh, unit=1.0)) == "my_rig"  # remembered for detection
    clash = tmp_path / "clash.yaml"
    clash.write_text("family: cmu_mb\njoints: {l_knee: A}\n")
    with pytest.raises(SkeletonMapError, match="built-in"):
        load_skeleton_map(clash)


@pytest.mark.parametrize("text, match", [
    ("family: x\njoints: {l_kne: A}\n", "not a human31 joint.*l_knee"),
    ("joints: {l_knee: A}\n", "'family'"),
    ("family: x\n", "'joints'"),
    ("family: x\nunit: -1\njoints: {l_knee: A}\n", "positive"),
    ("family: x\nformat: c3d\njoints: {l_knee: A}\n", "format"),
    ("family: [x\n", "not valid YAML"),
])
def test_exception_malformed_map(tmp_path, text, match):
    p = tmp_path / "m.yaml"
    p.write_text(text)
    with pytest.raises(SkeletonMapError, match=match):
        load_skeleton_map(p)


def test_exception_unknown_name():
    with pytest.raises(SkeletonMapError, match="built-in families"):
        load_skeleton_map("no_such_family")


def test_chain_height_sides(cmu):
    from torchmocap.io import read_amc

    clip = read_amc(cmu / "01_01.amc", cmu / "01.asf").slice(0, 2)
    # 01.asf: tibia + femur + hipjoint + lowerback + upperback + thorax + 2 necks + head
    left = (7.49137 + 7.1578 + 2.40479 + 2.04495 + 2.05008 + 2.06488 + 1.75553 + 1.76878
            + 1.77193) * 0.0254 / 0.45
    right = left + (7.50908 + 7.43386 + 2.37265 - 7.49137 - 7.1578 - 2.40479) * 0.0254 / 0.45
    assert chain_height(clip) == pytest.approx(left, abs=1e-9)
    assert chain_height(clip, side="right") == pytest.approx(right, abs=1e-9)
    with pytest.raises(ValueError, match="side"):
        chain_height(clip, side="middle")


def test_resolve_and_explicit_map_for_amc(cmu):
    from torchmocap.io import load_motion, resolve_skeleton_map

    clip = load_motion(cmu / "01_01.amc", skeleton_map="hdm05_asf").slice(0, 2)
    assert clip.skeleton_family == "hdm05_asf"  # the caller's label wins over detection
    assert resolve_skeleton_map(clip).family == "hdm05_asf"
    assert resolve_skeleton_map(clip, "cmu_asf").family == "cmu_asf"
    assert resolve_skeleton_map(["a", "b"]) is None
