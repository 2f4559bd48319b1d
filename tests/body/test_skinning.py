"""Skinned CC0 mesh: bundled asset, LBS on its own rig, driving by human31, export, rebuild."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from torchmocap.body import CapsuleBody
from torchmocap.body.skinning import (
    ASSET_PATH,
    HUMAN31_BONE_MAP,
    SkinnedBody,
    linear_blend_skinning,
    rotation_between,
)
from torchmocap.geometry import axis_angle_rotation, random_rotation_matrix
from torchmocap.skeleton import human31

F64 = torch.float64


@pytest.fixture(scope="module")
def body():
    return SkinnedBody()


@pytest.fixture(scope="module")
def sk():
    return human31()


def _rot(axis, angle):
    return axis_angle_rotation(torch.tensor(axis, dtype=F64), torch.tensor(angle, dtype=F64))


class TestAsset:
    def test_feature_bundled_asset(self, body):
        assert ASSET_PATH.stat().st_size < 1.5e6
        assert (ASSET_PATH.parent / "LICENSE.txt").read_text().count("CC0 1.0") == 1
        assert 3000 <= body.num_vertices <= 5000 and body.num_bones == 31
        mesh = body.to_trimesh()
        # closed enough to rasterise: no open boundary edges, (almost) one piece
        edges = np.sort(mesh.edges, axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert int((counts == 1).sum()) == 0
        assert len(mesh.split(only_watertight=False)) <= 3
        torch.testing.assert_close(body.weights.sum(1), torch.ones(body.num_vertices))
        assert bool((body.weights >= 0).all())

    def test_feature_world_frame(self, body):
        v = body.vertices
        height = float(v[:, 2].max() - v[:, 2].min())
        assert height == pytest.approx(1.67, abs=0.02)  # Z-up metres
        # facing -y: the toes and the nose are the most -y points of the feet and the head
        toe = body.joint_centre("joint-l-toe-3-1")
        ankle = body.joint_centre("joint-l-ankle")
        assert toe[1] < ankle[1] - 0.1
        # the person's left (LeftHand bone) is at +x; MakeHuman rest is an A-pose (arms ~45° down)
        lh = v[body.bone_weights("LeftHand") > 0.5]
        assert float(lh[:, 0].mean()) > 0.35
        arm = body.joint_centre("joint-l-elbow") - body.joint_centre("joint-l-shoulder")
        down = math.degrees(math.atan2(-float(arm[2]), float(arm[0])))
        assert 35 < down < 60
        # the bone rig's hierarchy: parents precede children, one root (Hips)
        assert body.bone_parents[0] == -1 and body.bone_names[0] == "Hips"
        assert all(p < i for i, p in enumerate(body.bone_parents))


class TestLBS:
    def test_feature_identity_is_rest(self, body):
        R = torch.eye(3, dtype=F64).expand(body.num_bones, 3, 3)
        torch.testing.assert_close(body.pose(R), body.vertices.double(), atol=1e-6, rtol=0)
        shift = torch.tensor([0.5, -1.0, 2.0], dtype=F64)
        torch.testing.assert_close(body.pose(R, body.bone_heads[0].double() + shift),
                                   body.vertices.double() + shift, atol=1e-6, rtol=0)

    def test_feature_rigid_rotation(self, body):
        g = torch.Generator().manual_seed(0)
        Rg = random_rotation_matrix((), generator=g, dtype=F64)
        R = Rg.expand(body.num_bones, 3, 3)
        v = body.pose(R, torch.zeros(3, dtype=F64))
        expect = (body.vertices.double() - body.bone_heads[0].double()) @ Rg.T
        torch.testing.assert_close(v, expect, atol=1e-6, rtol=0)

    def test_feature_knee_rotation_closed_form(self, body):
        R = torch.eye(3, dtype=F64).repeat(body.num_bones, 1, 1)
        b = body.bone_names.index("LeftLeg")
        Rk = _rot([1.0, 0, 0], 1.0)
        for i, name in enumerate(body.bone_names):  # the shank and its descendants
            if name in ("LeftLeg", "LeftFoot", "LeftToeBase"):
                R[i] = Rk
        v = body.pose(R)
        knee = body.bone_heads[b].double()
        rest = body.vertices.double()
        shank_ids = [body.bone_names.index(n) for n in ("LeftLeg", "LeftFoot", "LeftToeBase")]
        on_shank = body.weights.sum(1) - body.weights[:, shank_ids].sum(1) == 0
        assert int(on_shank.sum()) > 200
        torch.testing.assert_close(v[on_shank], (rest[on_shank] - knee) @ Rk.T + knee,
                                   atol=1e-6, rtol=0)
        untouched = body.weights[:, [body.bone_names.index(n) for n in
                                     ("LeftLeg", "LeftFoot", "LeftToeBase")]].sum(1) == 0
        torch.testing.assert_close(v[untouched], rest[untouched], atol=1e-6, rtol=0)

    def test_cardinality(self, body):
        R = torch.eye(3).expand(2, 5, body.num_bones, 3, 3)
        assert body.pose(R).shape == (2, 5, body.num_vertices, 3)

    def test_exception(self, body, sk):
        with pytest.raises(ValueError, match="bone_rotations"):
            body.pose(torch.eye(3).expand(3, 3, 3))
        with pytest.raises(ValueError, match="weights"):
            linear_blend_skinning(torch.zeros(4, 3), torch.zeros(3, 2), torch.zeros(2, 3, 3),
                                  torch.zeros(2, 3))
        with pytest.raises(FileNotFoundError, match="asset_path"):
            SkinnedBody("/nonexistent/body.npz")

    def test_gradcheck(self, body):
        verts = body.vertices.double()[:20]
        W = body.weights.double()[:20]
        R = random_rotation_matrix((body.num_bones,), generator=torch.Generator().manual_seed(1),
                                   dtype=F64).requires_grad_(True)
        t = torch.randn(body.num_bones, 3, dtype=F64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda r, tt: linear_blend_skinning(verts, W, r, tt),
                                        (R, t))


class TestRotationBetween:
    def test_feature(self):
        g = torch.Generator().manual_seed(0)
        a = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=F64), dim=-1)
        b = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=F64), dim=-1)
        b[0] = -a[0]  # antiparallel
        b[1] = a[1]
        R = rotation_between(a, b)
        torch.testing.assert_close((R @ a[..., None])[..., 0], b)
        eye = torch.eye(3, dtype=F64).expand(50, 3, 3)
        torch.testing.assert_close(R @ R.transpose(-1, -2), eye)
        torch.testing.assert_close(torch.linalg.det(R), torch.ones(50, dtype=F64))


class TestDrivenByHuman31:
    def test_feature_zero_pose_is_aligned_rest(self, body, sk):
        th = sk.zero_pose(dtype=F64)
        v = body.pose_from_skeleton(sk, th)
        kin = sk(th)
        bind = body.bind(sk)
        assert bind.scale == pytest.approx(1.05, abs=0.03)
        # mesh joint centres land on the skeleton joints (rest alignment), e.g. the knee cube
        # carried by the thigh's transform reaches the skeleton knee
        for j, (_cube, end, skel_end) in [("l_hip", ("joint-l-upper-leg", "joint-l-knee",
                                                    "l_knee")),
                                         ("r_elbow", ("joint-r-elbow", "joint-r-hand",
                                                      "r_wrist"))]:
            k = bind.joint_index.tolist().index(sk.joint_index(j))
            m_end = body.joint_centre(end).double()
            mapped = kin.positions[sk.joint_index(j)] + bind.linear[k] @ (
                m_end - bind.mesh_origin[k])
            torch.testing.assert_close(mapped, kin.positions[sk.joint_index(skel_end)])
        # rest alignment straightens the A-pose arms: hands hang beside the hips
        lh = v[body.bone_weights("LeftHand") > 0.5]
        assert float(lh[:, 0].mean()) < 0.3 and float(lh[:, 2].mean()) < 0.95
        # stature matches the skeleton (head top 1.75 m), soles near the floor
        assert float(v[:, 2].max()) == pytest.approx(1.75, abs=0.03)
        assert abs(float(v[:, 2].min())) < 0.03
        # each vertex is the weighted blend of p_j + M_j (x - m_j) over its joints
        x = body.vertices.double()
        for i in [0, 1000, 2500, 4000]:
            expect = sum(float(bind.weights[i, k]) * (
                kin.positions[int(j)] + bind.linear[k] @ (x[i] - bind.mesh_origin[k]))
                for k, j in enumerate(bind.joint_index))
            torch.testing.assert_close(v[i], expect)
        # the pelvis joint carries the hips without rotation, only the stature scale
        k0 = bind.joint_index.tolist().index(0)
        torch.testing.assert_close(bind.linear[k0], bind.scale * torch.eye(3, dtype=F64))

    def test_feature_knee_moves_only_leg(self, body, sk):
        th = sk.zero_pose(dtype=F64)
        v0 = body.pose_from_skeleton(sk, th)
        th2 = th.clone()
        th2[sk.dof_index("l_knee_flex")] = 1.2
        v1 = body.pose_from_skeleton(sk, th2)
        moved = (v1 - v0).norm(dim=-1) > 1e-9
        leg = sum(body.bone_weights(n) for n in ("LeftLeg", "LeftFoot", "LeftToeBase")) > 0
        assert bool(moved.any())
        assert not bool((moved & ~leg).any())  # only vertices skinned to the left shank/foot move
        shank = body.bone_weights("LeftLeg") > 0.999
        assert float((v1 - v0)[shank].norm(dim=-1).mean()) > 0.1
        right = body.bone_weights("RightLeg") > 0
        assert float((v1 - v0)[right].abs().max()) == 0.0
        # the foot swings backwards (+y) when the knee flexes
        foot = body.bone_weights("LeftFoot") > 0.999
        assert float((v1 - v0)[foot][:, 1].mean()) > 0.2

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_feature_close_to_capsule_body(self, body, sk, seed):
        caps = CapsuleBody(sk)
        g = torch.Generator().manual_seed(seed)
        th = sk.zero_pose(dtype=F64)
        if seed:
            th = sk.clamp(0.4 * torch.randn(sk.num_dofs, generator=g, dtype=F64))
            th[:3] = torch.tensor([0.3, -0.2, 0.1], dtype=F64)
        v = body.pose_from_skeleton(sk, th)
        d = caps.skin_distance(v, sk(th))
        assert float(d.abs().mean()) < 0.04, float(d.abs().mean())
        assert float(d.median().abs()) < 0.02
        assert float(d.max()) < 0.12

    def test_feature_batched_and_scaled(self, body, sk):
        g = torch.Generator().manual_seed(5)
        th = sk.clamp(0.3 * torch.randn(3, 2, sk.num_dofs, generator=g, dtype=F64))
        v = body.pose_from_skeleton(sk, th)
        assert v.shape == (3, 2, body.num_vertices, 3)
        torch.testing.assert_close(v[1, 1], body.pose_from_skeleton(sk, th[1, 1]))
        # the cached binding follows offset changes of the same skeleton object
        sk2 = human31()
        v_before = body.pose_from_skeleton(sk2, sk2.zero_pose(dtype=F64))
        with torch.no_grad():
            sk2.offsets.mul_(0.9)
        v_after = body.pose_from_skeleton(sk2, sk2.zero_pose(dtype=F64))
        assert float(v_after[:, 2].max()) == pytest.approx(0.9 * float(v_before[:, 2].max()),
                                                           abs=0.02)
        small = sk.with_bone_lengths(scale=0.8)
        vs = body.pose_from_skeleton(small, small.zero_pose(dtype=F64))
        assert float(vs[:, 2].max()) == pytest.approx(0.8 * 1.75, abs=0.03)

    def test_feature_every_mesh_bone_is_mapped(self, body):
        assert set(HUMAN31_BONE_MAP) == set(body.bone_names)

    def test_exception(self, body):
        from torchmocap.skeleton import upper_body

        with pytest.raises(ValueError, match="skeleton"):
            body.bind(upper_body())


class TestExport:
    @pytest.mark.parametrize("suffix", [".obj", ".glb"])
    def test_feature_round_trip(self, body, sk, tmp_path, suffix):
        th = sk.zero_pose(dtype=F64)
        th[sk.dof_index("r_shoulder_flex")] = 1.0
        v = body.pose_from_skeleton(sk, th)
        path = body.export(tmp_path / f"body{suffix}", v)
        loaded = trimesh.load(path, force="mesh", process=False)
        assert len(loaded.faces) == body.faces.shape[0]
        np.testing.assert_allclose(np.sort(loaded.vertices[:, 2]),
                                   np.sort(v[:, 2].numpy()), atol=1e-5)

    def test_exception(self, body):
        with pytest.raises(ValueError, match="vertices"):
            body.to_trimesh(torch.zeros(5, 3))


def test_build_script_reproduces_asset(tmp_path, makehuman_dir):
    import fast_simplification  # noqa: F401  (dev extra: a missing one must fail, not skip)

    from torchmocap.body.asset_build import build_body_asset, load_makehuman_source

    full = load_makehuman_source(makehuman_dir)
    assert full["vertices"].shape == (13380, 3) and len(full["bone_names"]) == 31
    # every skin vertex carries weight, none on the other side's bones; the skin is watertight
    assert (full["weights"].sum(1) > 0.99).all()
    names = full["bone_names"]
    left = [i for i, n in enumerate(names) if n.startswith("Left")]
    assert full["weights"][full["vertices"][:, 0] < -0.03][:, left].max() == 0
    assert trimesh.Trimesh(full["vertices"], full["faces"], process=False).is_watertight
    stats = build_body_asset(makehuman_dir, tmp_path / "b.npz")
    assert stats["bytes"] < 1.5e6 and 3000 < stats["vertices"] < 5000
    rebuilt = SkinnedBody(tmp_path / "b.npz")
    bundled = SkinnedBody()
    assert rebuilt.num_vertices == bundled.num_vertices
    torch.testing.assert_close(rebuilt.joint_centres, bundled.joint_centres)


def test_device(device):
    sk = human31().to(device)
    body = SkinnedBody().to(device)
    v = body.pose_from_skeleton(sk, sk.zero_pose((2,), device=device))
    assert v.device.type == device.type and v.shape == (2, body.num_vertices, 3)
