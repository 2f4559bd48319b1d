"""Skeleton maps: built-in YAMLs, detection, user maps, and the error for unknown skeletons."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest
import torch

from torchmocap.io import (
    HUMAN31_JOINTS,
    MotionClip,
    SkeletonMapError,
    chain_height,
    detect_family,
    guess_joint_map,
    guess_joints,
    guessed_joints,
    human31_positions,
    joint_map_report,
    known_families,
    load_skeleton_map,
    map_joints,
    read_bvh,
    unmapped_joints,
    write_bvh,
)
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parent))
from synthetic_bvh import (  # noqa: E402
    CONVENTIONS,
    human31_motion,
    names_for,
    write_unseen_family_bvh,
)

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
    odd = _renamed(walk, {"LeftKnee": "Gelenk_7", "Head_end": "Kopf_Spitze",
                          "LeftToe": "Zeh_j", "Hips": "Hips"})
    assert detect_family(odd) is None
    assert unmapped_joints(odd) == ["head_top", "l_knee", "l_toe"]
    with pytest.raises(SkeletonMapError) as e:
        map_joints(odd)
    msg = str(e.value)
    assert "cannot map 3 human31 joint(s): ['head_top', 'l_knee', 'l_toe']" in msg
    for h in ("head_top", "l_knee", "l_toe"):
        assert f"  {h}: closest source joints " in msg
    assert "docs/skeleton_maps.md" in msg
    assert "RightKnee" not in msg.split("l_knee:")[1].split("\n")[0]  # wrong side not offered
    with pytest.raises(SkeletonMapError):
        chain_height(odd)
    # guessing works where names are known spellings
    assert guess_joint_map(odd)["r_knee"] == "RightKnee"


def test_guess_understands_decorated_spellings(walk):
    """``L_Knee_jnt``, ``HeadTop_tip``, ``lToe_j`` (rejected before) are read by their words."""
    odd = _renamed(walk, {"LeftKnee": "L_Knee_jnt", "Head_end": "HeadTop_tip",
                          "LeftToe": "lToe_j"})
    g = guess_joints(odd)
    assert g.complete
    assert (g.joints["l_knee"], g.joints["head_top"], g.joints["l_toe"]) == (
        "L_Knee_jnt", "HeadTop_tip", "lToe_j")
    # the 3dsMax-style CMU names alone give the built-in map (hands: the hand joint, not the
    # finger base the map picked)
    ref = dict(load_skeleton_map("cmu_max").joints)
    ref.update(l_hand="lhand", r_hand="rhand")
    assert guess_joints(walk).joints == ref
    assert map_joints(odd) == {h: odd.joint_names.index(v) for h, v in g.joints.items()}
    assert guessed_joints(odd) == list(HUMAN31_JOINTS) and guessed_joints(walk) == []


@pytest.mark.parametrize("convention", sorted(CONVENTIONS))
@pytest.mark.parametrize("end_length", [0.0, 0.09], ids=["zero_end_sites", "end_sites"])
def test_guess_unseen_families(tmp_path, convention, end_length):
    """A 22-joint skeleton of no built-in family, named by a common convention, maps onto
    human31 by its names alone; its mapped joints are human31's (the skeleton has human31's
    geometry and motion) and the subject fit reproduces them."""
    from torchmocap.data.subjects.mocap import fit_subject

    path = write_unseen_family_bvh(tmp_path / f"{convention}.bvh", convention,
                                   end_length=end_length)
    clip = read_bvh(path, unit=0.01)
    assert clip.num_joints == 22 + 5 and detect_family(clip) is None
    roles = names_for(convention)
    g = guess_joints(clip)
    assert g.complete, (g.missing, g.ambiguous)
    expect = {h: roles[h] for h in HUMAN31_JOINTS if h in roles}
    expect.update(head_top=f"{roles['head']}_end", l_hand=f"{roles['l_wrist']}_end",
                  r_hand=f"{roles['r_wrist']}_end")
    assert g.joints == expect
    report = joint_map_report(clip)
    assert report["source"] == "guessed" and report["guessed_joints"] == list(HUMAN31_JOINTS)
    assert report["unmapped_joints"] == [] and report["joints"] == expect
    # FK of the mapped joints = human31's FK of the driving poses (exact geometry)
    sk = human31().double()
    p_ref = sk(human31_motion(clip.num_frames)).positions
    p = human31_positions(clip)
    body = [i for i, h in enumerate(HUMAN31_JOINTS) if end_length or h not in (
        "head_top", "l_hand", "r_hand")]
    torch.testing.assert_close(p[:, body], p_ref[:, body], atol=1e-5, rtol=0)
    fit = fit_subject(clip, iterations=20)
    assert float(fit.residual.max()) < 1e-4
    assert fit.info["guessed_joints"] == list(HUMAN31_JOINTS)


def test_vendored_unseen_family_file_is_reproducible(tmp_path, shared_data):
    """tests/data_files/synthetic/unseen22_suffix_L.bvh is what the helper writes."""
    path = write_unseen_family_bvh(tmp_path / "u.bvh", "suffix_underscore", frames=6)
    committed = shared_data / "synthetic" / "unseen22_suffix_L.bvh"
    assert committed.read_text() == path.read_text()
    clip = read_bvh(committed, unit=0.01)
    assert len([n for n in clip.joint_names if not n.endswith("_end")]) == 22
    assert guess_joints(clip).complete


@pytest.mark.parametrize("rename, joint, candidates", [
    ({"l_clavicle": "Arm_L"}, "l_shoulder", ["Arm_L", "UpperArm_L"]),
    ({"l_knee": "Shin_L", "l_ankle": "Calf_L"}, "l_knee", ["Shin_L", "Calf_L"]),
])
def test_guess_refuses_ambiguous_names(tmp_path, rename, joint, candidates):
    path = write_unseen_family_bvh(tmp_path / "amb.bvh", "suffix_underscore", rename=rename)
    clip = read_bvh(path, unit=0.01)
    g = guess_joints(clip)
    assert g.ambiguous == {joint: tuple(candidates)} and joint not in g.joints
    assert joint in unmapped_joints(clip)
    with pytest.raises(SkeletonMapError, match=re.escape(
            f"{joint}: ambiguous, candidates {candidates}")):
        map_joints(clip)


@pytest.mark.parametrize("name, side, core", [
    ("mixamorig:LeftUpLeg", "l", "upleg"), ("UpperArm_L", "l", "upperarm"),
    ("thigh.R", "r", "thigh"), ("lShldr", "l", "shldr"), ("LHipJoint", "l", "hipjoint"),
    ("lfemur", "l", "femur"), ("rtoes", "r", "toes"), ("lowerback", None, "lowerback"),
    ("Bip01 R Calf", "r", "calf"), ("RIGHT_FOREARM", "r", "forearm"), ("KneeL", "l", "knee"),
    ("leg", None, "leg"), ("Left Hand_end", "l", "hand"), ("spine.002", None, "spine"),
])
def test_name_parsing(name, side, core):
    from torchmocap.io.skeleton_maps import _parse_name

    n = _parse_name(name)
    assert (n.side, n.core) == (side, core)


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


def test_exception_binary_or_malformed_map_file(tmp_path):
    """A binary file given as a skeleton map failed with a bare UTF-8 decode error, a malformed
    one with a multi-line YAML report whose first line named nothing."""
    p = tmp_path / "mine.yaml"
    p.write_bytes(b"family: x\n\xbf\xff\x00")
    with pytest.raises(SkeletonMapError, match=r"mine\.yaml: not a text file \(byte 0xbf at "
                                               r"offset 10 is not UTF-8\); expected a skeleton "
                                               r"map"):
        load_skeleton_map(p)
    p.write_text("family: x\njoints: {pelvis: Hips\nbones: [a]\n")
    with pytest.raises(SkeletonMapError, match=r"^\S*mine\.yaml: not valid YAML \(line 3, "
                                               r"column 6: "):
        load_skeleton_map(p)
