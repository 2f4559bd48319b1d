"""Keypoints from the surface: the vertex sets sit where their names say on every phenotype, the
rigid offsets they give follow the skinned surface in a pose, and the keypoint term reads them
off the body fit's phenotype (the others keep the map's offsets)."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body.surface_keypoints import (
    KEYPOINT_POINTS,
    SURFACE_POINTS,
    surface_keypoint_map,
    surface_keypoint_offsets,
    surface_points,
    surface_vertex_sets,
)
from torchmocap.skeleton import keypoint_positions, load_keypoint_map

PHENOTYPES = [None, {"age": 0.25, "height": 0.3}, {"gender": 1.0, "weight": 0.9},
              {"gender": 0.0, "height": 0.95, "proportions": 0.8}]


def _rest(body, phen):
    sk = body.skeleton
    pose = body(sk.zero_pose(dtype=torch.float64), body.phenotype_tensor(phen).double(),
                offsets=sk.offsets.double())
    return pose, surface_points(body, pose.vertices)


def test_smoke(anny_body):
    sets = surface_vertex_sets(anny_body)
    assert set(sets) == set(SURFACE_POINTS)
    assert all(v.numel() >= 5 and v.dtype == torch.int64 for v in sets.values())
    assert set(KEYPOINT_POINTS.values()) <= set(SURFACE_POINTS)


@pytest.mark.parametrize("phen", PHENOTYPES)
def test_feature_points_sit_where_their_names_say(anny_body, phen):
    """World frame at the rest pose: +x the subject's left, -y forward, +z up."""
    pose, p = _rest(anny_body, phen)
    names = list(anny_body.joint_names)
    j = {n: pose.kinematics.positions[names.index(n)] for n in names}
    v = pose.vertices
    for name, x in p.items():  # on (or within a centimetre of) the skin
        assert float((v - x).norm(dim=-1).min()) < 0.012, name
    head = [p[k] for k in ("nose", "l_eye", "r_eye", "l_ear", "r_ear")]
    assert all(float(p["head_top"][2]) > float(x[2]) + 0.05 for x in head)
    assert float(p["nose"][1]) < min(float(p["l_eye"][1]), float(p["r_eye"][1]))  # foremost
    assert float(p["nose"][2]) < float(p["l_eye"][2])
    assert abs(float(p["nose"][0])) < 0.005
    for s, sign in (("l", 1.0), ("r", -1.0)):
        assert sign * float(p[f"{s}_ear"][0]) > sign * float(p[f"{s}_eye"][0]) + 0.03
        assert float(p[f"{s}_ear"][1]) > float(p[f"{s}_eye"][1]) + 0.04  # behind the eyes
        ankle, toe = j[f"{s}_ankle"], j[f"{s}_toe"]
        assert float(p[f"{s}_heel"][1]) > float(ankle[1]) + 0.03  # behind the ankle
        assert float(p[f"{s}_heel"][2]) < float(ankle[2])
        assert float(p[f"{s}_big_toe"][1]) < float(toe[1]) - 0.02  # ahead of the ball
        # the big toe medial (towards the midline) of the little toe, and ahead of it
        assert sign * float(p[f"{s}_big_toe"][0]) < sign * float(p[f"{s}_small_toe"][0]) - 0.03
        assert float(p[f"{s}_big_toe"][1]) < float(p[f"{s}_small_toe"][1])
    # left and right mirror each other
    for s in ("eye", "ear", "heel", "big_toe", "small_toe"):
        a, b = p[f"l_{s}"], p[f"r_{s}"]
        assert float((a * torch.tensor([-1.0, 1, 1], dtype=a.dtype) - b).norm()) < 0.01, s


def test_feature_offsets_follow_the_skinned_surface(anny_body):
    """The offsets place each keypoint on its bone rigidly: in a pose (head turned and bent,
    ankles flexed, knees bent) the keypoint stays within 1.5 cm of its skinned vertices."""
    sk = anny_body.skeleton
    km = load_keypoint_map("body_25b", sk)
    phen = anny_body.phenotype_tensor({"age": 0.4, "weight": 0.7}).double()
    off, placed = surface_keypoint_offsets(km, anny_body, phen, sk.offsets)
    assert set(placed) == {n for n in km.names if n in KEYPOINT_POINTS}
    theta = sk.zero_pose(dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    theta = theta + 0.25 * torch.randn(theta.shape, generator=g, dtype=theta.dtype)
    pose = anny_body(theta, phen, offsets=sk.offsets.double())
    pts = surface_points(anny_body, pose.vertices)
    x = keypoint_positions(pose.kinematics.positions, pose.kinematics.rotations, km, off)
    head = [k for k, n in enumerate(km.names) if n in placed and km.joints[k] == "head"]
    for k, name in enumerate(km.names):
        if name in placed and k not in head:
            assert float((x[k] - pts[KEYPOINT_POINTS[name]]).norm()) < 0.015, name
    # the head's points are one translation away from the skin (the eye-height convention):
    # their differences follow the skinned surface
    skin = torch.stack([pts[KEYPOINT_POINTS[km.names[k]]] for k in head])
    shift = (x[head] - skin).mean(0)
    assert float((x[head] - skin - shift).norm(dim=-1).max()) < 0.015
    assert 0.01 < float(shift.norm()) < 0.06
    # the keypoints without a surface point keep the map's offsets
    keep = [k for k, n in enumerate(km.names) if n not in placed]
    torch.testing.assert_close(off[keep], km.offsets[keep].double())
    sm = surface_keypoint_map(km, anny_body, phen, sk.offsets)
    torch.testing.assert_close(sm.offsets, off)


@pytest.mark.parametrize("phen", PHENOTYPES)
def test_feature_eyes_at_the_head_joints_height(anny_body, phen):
    """human31's convention (the maps' and the subject fit's): the head joint at eye height;
    the face keeps its shape (nose below the eyes, ears behind them)."""
    sk = anny_body.skeleton
    km = load_keypoint_map("body_25b", sk)
    off, _ = surface_keypoint_offsets(km, anny_body, anny_body.phenotype_tensor(phen).double(),
                                      sk.offsets)
    o = {n: off[k] for k, n in enumerate(km.names)}
    assert abs(float(o["LEye"][2] + o["REye"][2])) < 1e-9
    assert float(o["Nose"][2]) < -0.01 and float(o["Nose"][1]) < float(o["LEye"][1])
    assert float(o["LEar"][1]) > float(o["LEye"][1]) + 0.04


def test_feature_the_term_reads_the_fitted_phenotype(anny_body):
    """A keypoint term with surface_keypoints keeps the map's offsets until a body fit sets the
    phenotype on the runtime body, then scores detections made from the surface at the true
    pose better than the map does."""
    from types import SimpleNamespace

    from torchmocap.cameras import make_ring_rig
    from torchmocap.data import Frame
    from torchmocap.likelihoods import KeypointLikelihood
    from torchmocap.likelihoods.base import Poses

    sk = anny_body.skeleton
    rig = make_ring_rig(4).double()
    body = SimpleNamespace(skeleton=sk, surface_phenotype=None)
    term = KeypointLikelihood(rig, sk, keypoint_map="body_25b", surface_keypoints=True,
                              surface_anchor="joint",
                              body=body, cache_dir=str(anny_body.data_path.parent))
    plain = KeypointLikelihood(rig, sk, keypoint_map="body_25b")
    km = term.kmap
    theta = sk.zero_pose((1,), dtype=torch.float64)
    poses = Poses(theta, sk)
    torch.testing.assert_close(term.keypoints(poses), plain.keypoints(poses).to(torch.float64))
    assert term.surface_placed == []
    phen = anny_body.phenotype_tensor({"age": 0.3, "height": 0.8}).double()
    body.surface_phenotype = phen
    off, _ = surface_keypoint_offsets(km, anny_body, phen, sk.offsets)
    kin = sk(theta.double())
    x = keypoint_positions(kin.positions, kin.rotations, km, off)[0]
    pix = rig.project(x)[0]
    j2d = torch.zeros(4, len(term.keypoint_names), 3, dtype=torch.float64)
    j2d[:, term.columns, :2] = pix
    j2d[:, term.columns, 2] = 1.0
    frame = Frame(0, 0.0, joints2d=j2d)
    e_surface = term.energy(poses, term.prepare(frame))
    e_map = plain.energy(poses, plain.prepare(frame))
    assert sorted(term.surface_placed) == sorted(n for n in km.names if n in KEYPOINT_POINTS)
    assert float(e_surface) < 1e-6 < float(e_map)
    changed = (term.offsets.detach().double() - km.offsets.double()).norm(dim=-1) > 1e-6
    assert {km.names[k] for k in torch.nonzero(changed).flatten().tolist()} <= \
        set(term.surface_placed)


def test_exception_bad_settings(anny_body):
    from torchmocap.cameras import make_ring_rig
    from torchmocap.likelihoods import KeypointLikelihood
    from torchmocap.skeleton import human31

    rig = make_ring_rig(2)
    with pytest.raises(ValueError, match="learn_offsets"):
        KeypointLikelihood(rig, human31(), surface_keypoints=True, learn_offsets=True,
                           body=object())
    with pytest.raises(ValueError, match="runtime body"):
        KeypointLikelihood(rig, human31(), surface_keypoints=True)
    with pytest.raises(ValueError, match="surface_keypoints: expected true or false"):
        KeypointLikelihood(rig, human31(), surface_keypoints="yes", body=object())
    km = load_keypoint_map("body_25b", human31())
    other = km.__class__(**{**km.__dict__, "skeleton_joints": tuple(f"x{i}" for i in
                                                                    range(len(km.skeleton_joints)))})
    with pytest.raises(ValueError, match="kmap: bound to joints"):
        surface_keypoint_offsets(other, anny_body, anny_body.phenotype_tensor(None),
                                 anny_body.skeleton.offsets)
    with pytest.raises(ValueError, match="phenotype: expected shape"):
        surface_keypoint_offsets(km, anny_body, torch.zeros(3), anny_body.skeleton.offsets)


def test_feature_map_anchor_keeps_each_groups_place(anny_body):
    """anchor='map': each joint's group of surface keypoints keeps the map's mean offset and
    the surface's shape; a keypoint alone on its joint keeps the map's offset."""
    sk = anny_body.skeleton
    km = load_keypoint_map("body_25b", sk)
    phen = anny_body.phenotype_tensor({"age": 0.3}).double()
    joint, placed = surface_keypoint_offsets(km, anny_body, phen, sk.offsets)
    mapped, _ = surface_keypoint_offsets(km, anny_body, phen, sk.offsets, anchor="map")
    given = km.offsets.double()
    face = [km.names.index(n) for n in ("Nose", "LEye", "REye", "LEar", "REar")]
    torch.testing.assert_close(mapped[face].mean(0), given[face].mean(0))
    torch.testing.assert_close(mapped[face] - mapped[face].mean(0),
                               joint[face] - joint[face].mean(0))
    for alone in ("Head", "LHeel", "RHeel"):
        k = km.names.index(alone)
        torch.testing.assert_close(mapped[k], given[k])
    assert float((mapped[face] - given[face]).norm(dim=-1).max()) > 0.005  # the shape moved
    with pytest.raises(ValueError, match="anchor: expected"):
        surface_keypoint_offsets(km, anny_body, phen, sk.offsets, anchor="middle")
