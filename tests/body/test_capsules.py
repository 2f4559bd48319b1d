"""Capsule body: closed-form distances, gradcheck, shapes, surface sampling, mesh export."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from torchmocap.body import (
    CapsuleBody,
    anthropometric_radii,
    capsule_distance,
    capsule_endpoints,
    facing_camera,
    sample_capsule_surface,
    segment_closest_points,
    segment_distance,
)
from torchmocap.skeleton import Skeleton, human31

F64 = torch.float64


@pytest.fixture(scope="module")
def sk():
    return human31()


def _unit_capsule():
    return torch.tensor([[[0.0, 0, 0], [0, 0, 1]]], dtype=F64), torch.tensor([0.1], dtype=F64)


class TestCapsuleDistance:
    def test_feature_closed_form(self):
        e, r = _unit_capsule()
        pts = torch.tensor([[1.0, 0, 0.5],    # beside the cylinder: 1 - 0.1
                            [0, 0, 2.0],      # above the top cap: 1 - 0.1
                            [0, 3.0, -4.0],   # beyond the bottom cap: 5 - 0.1
                            [0.05, 0, 0.5],   # inside: 0.05 - 0.1
                            [0.6, 0.8, 0.3]], dtype=F64)
        d = capsule_distance(pts, e, r)
        torch.testing.assert_close(d, torch.tensor([0.9, 0.9, 4.9, -0.05, 0.9], dtype=F64))

    def test_feature_union_is_min(self):
        e = torch.tensor([[[0.0, 0, 0], [0, 0, 1]], [[1.0, 0, 0], [1, 0, 1]]], dtype=F64)
        r = torch.tensor([0.1, 0.3], dtype=F64)
        pts = torch.tensor([[0.5, 0, 0.5], [0.2, 0, 0.5], [-1.0, 0, 0.5]], dtype=F64)
        per = capsule_distance(pts, e, r, reduce=False)
        torch.testing.assert_close(per, torch.tensor([[0.4, 0.2], [0.1, 0.5], [0.9, 1.7]],
                                                     dtype=F64))
        torch.testing.assert_close(capsule_distance(pts, e, r),
                                   torch.tensor([0.2, 0.1, 0.9], dtype=F64))

    def test_feature_fast_segment_distance_matches_explicit(self):
        g = torch.Generator().manual_seed(7)
        ep = torch.randn(4, 6, 2, 3, generator=g, dtype=F64) + 2.0  # offset: cancellation test
        pts = torch.randn(4, 50, 3, generator=g, dtype=F64) + 2.0
        closest, s = segment_closest_points(pts, ep)
        ref = (pts[..., :, None, :] - closest).norm(dim=-1)
        torch.testing.assert_close(segment_distance(pts, ep), ref)
        assert bool(((s > 0) & (s < 1)).any()) and bool((s == 0).any()) and bool((s == 1).any())
        d32 = segment_distance(pts.float(), ep.float())
        assert (d32.double() - ref).abs().max() < 2e-5

    def test_feature_camera_facing_half(self):
        e, r = _unit_capsule()
        cam = torch.tensor([5.0, 0, 0.5], dtype=F64)
        # in front (camera side): same as the full distance
        front = torch.tensor([[0.5, 0, 0.5]], dtype=F64)
        torch.testing.assert_close(capsule_distance(front, e, r, cam),
                                   torch.tensor([0.4], dtype=F64))
        # behind the capsule: the nearest visible skin is the rim at (0, ±0.1, z)
        back = torch.tensor([[-0.5, 0, 0.5]], dtype=F64)
        torch.testing.assert_close(capsule_distance(back, e, r, cam),
                                   torch.tensor([math.hypot(0.5, 0.1)], dtype=F64))
        assert capsule_distance(back, e, r).item() == pytest.approx(0.4)
        # a point inside measures the distance to the surface (unsigned)
        inside = torch.tensor([[0.02, 0, 0.5]], dtype=F64)
        torch.testing.assert_close(capsule_distance(inside, e, r, cam),
                                   torch.tensor([0.08], dtype=F64))

    def test_feature_facing_half_matches_explicit_geometry(self):
        # the dot-product form against the surface construction it replaces: closest axis
        # point, outward normal, facing test, rim points s +- r w built as 3-vectors
        g = torch.Generator().manual_seed(3)
        ep = torch.randn(4, 7, 2, 3, generator=g, dtype=F64) * 0.4 + 2.0
        r = torch.rand(7, generator=g, dtype=F64) * 0.1 + 0.02
        pts = torch.randn(4, 300, 3, generator=g, dtype=F64) * 0.5 + 2.0
        cam = torch.tensor([[2.0, -3.0, 2.5]], dtype=F64).expand(4, 3)
        ep[0, 0, 1] = ep[0, 0, 0]  # a zero-length axis (a sphere)
        ep[1, 1, 1] = ep[1, 1, 0] + 0.3 * (cam[1] - ep[1, 1, 0])  # axis through the camera
        closest, _ = segment_closest_points(pts, ep)
        diff = pts[..., :, None, :] - closest
        dist = diff.norm(dim=-1)
        n = diff / dist[..., None]
        c = cam[:, None, None, :]
        facing = ((c - (closest + r[:, None] * n)) * n).sum(-1) >= 0
        axis = ep[..., None, :, 1, :] - ep[..., None, :, 0, :]
        axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        w = torch.linalg.cross(axis.expand_as(diff), c - closest)
        wn = w.norm(dim=-1, keepdim=True)
        w = torch.where(wn > 1e-9, w / wn, n)
        rim = torch.minimum((diff - r[:, None] * w).norm(dim=-1),
                            (diff + r[:, None] * w).norm(dim=-1))
        ref = torch.where(facing, (dist - r).abs(), rim)
        assert bool(facing.any()) and bool((~facing).any())
        got = capsule_distance(pts, ep, r, cam, reduce=False)
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-9)
        torch.testing.assert_close(capsule_distance(pts, ep, r, cam), ref.min(-1).values)
        # float32, far from the origin: the centring keeps the error at micrometres (the
        # axis through the camera is left out: there the rim direction is rounding noise)
        off = torch.tensor([3.0, 4.0, 1.0], dtype=F64)
        d32 = capsule_distance((pts + off).float(), (ep + off).float(), r.float(),
                               (cam + off).float(), reduce=False)
        err = (d32.double() - ref).abs()
        err[1, :, 1] = 0.0
        assert err.max() < 2e-5

    def test_cardinality(self, sk):
        body = CapsuleBody(sk)
        theta = sk.zero_pose((3, 4), dtype=F64)
        kin = sk(theta)
        pts = torch.randn(3, 4, 10, 3, dtype=F64)
        assert body.endpoints(kin).shape == (3, 4, body.num_bones, 2, 3)
        assert body.point_to_skin_distance(pts, kin).shape == (3, 4, 10)
        # shared points broadcast against particles
        assert body.point_to_skin_distance(pts[0, 0], kin).shape == (3, 4, 10)
        cam = torch.tensor([0.0, -4.0, 1.5], dtype=F64)
        assert body.skin_distance(pts, kin, cam).shape == (3, 4, 10)

    def test_exception(self):
        e, r = _unit_capsule()
        with pytest.raises(ValueError, match="points"):
            capsule_distance(torch.zeros(3, 2), e, r)
        with pytest.raises(ValueError, match="endpoints"):
            capsule_distance(torch.zeros(3, 3), torch.zeros(1, 3, 3), r)
        with pytest.raises(ValueError, match="radii"):
            capsule_distance(torch.zeros(3, 3, dtype=F64), e, torch.ones(2, dtype=F64))

    def test_gradcheck(self, sk):
        body = CapsuleBody(sk)
        g = torch.Generator().manual_seed(0)
        theta = (0.2 * torch.randn(2, sk.num_dofs, generator=g, dtype=F64)).requires_grad_(True)
        pts = (torch.randn(5, 3, generator=g, dtype=F64) * 0.3 +
               torch.tensor([0, 0, 1.0], dtype=F64)).requires_grad_(True)
        assert torch.autograd.gradcheck(lambda th, p: body.skin_distance(p, sk(th)), (theta, pts))
        cam = torch.tensor([0.3, -4.0, 1.5], dtype=F64)
        assert torch.autograd.gradcheck(lambda th, p: body.skin_distance(p, sk(th), cam),
                                        (theta, pts))

    def test_module(self, sk):
        body = CapsuleBody(sk)
        theta = 0.1 * torch.randn(4, sk.num_dofs, dtype=F64)
        kin = sk(theta)
        pts = torch.randn(4, 6, 3, dtype=F64)
        ep = capsule_endpoints(kin.positions, body.parent_index, body.child_index,
                               body.end_shrink)
        torch.testing.assert_close(body(theta), ep)
        torch.testing.assert_close(body.skin_distance(pts, kin),
                                   capsule_distance(pts, ep, body.radii))
        # Kinematics or plain positions are both accepted
        torch.testing.assert_close(body.endpoints(kin.positions), ep)


class TestAxisOffsets:
    def test_feature_offset_moves_the_capsule_in_the_parent_frame(self, sk):
        g = torch.Generator().manual_seed(3)
        theta = 0.4 * torch.randn(4, sk.num_dofs, generator=g, dtype=F64)
        kin = sk(theta)
        plain = CapsuleBody(sk).double()
        off = {"head_top": [0.0, -0.05, 0.01], "l_elbow": [0.02, 0.0, 0.0]}
        body = CapsuleBody(sk, axis_offsets=off).double()
        assert body.has_axis_offsets and not plain.has_axis_offsets
        ep, ep0 = body.endpoints(kin), plain.endpoints(kin)
        for b, v in off.items():
            i = body.bone_names.index(b)
            R = kin.rotations[:, sk.joint_names.index(sk.joint_names[
                sk.parents[sk.joint_names.index(b)]])]  # (4, 3, 3) the parent joint's frame
            shift = R @ torch.tensor(v, dtype=F64)
            torch.testing.assert_close(ep[:, i], ep0[:, i] + shift[:, None])
        others = [i for i, b in enumerate(body.bone_names) if b not in off]
        torch.testing.assert_close(ep[:, others], ep0[:, others])
        # the offset is rigid with the parent: the distance from the parent joint is kept
        i = body.bone_names.index("head_top")
        head = kin.positions[:, sk.joint_names.index("head")]
        d = (ep[:, i, 0] - head).norm(dim=-1)
        torch.testing.assert_close(d, torch.full_like(d, math.hypot(0.05, 0.01)))
        assert torch.autograd.gradcheck(
            lambda th: body.skin_distance(torch.tensor([[0.1, -0.2, 1.6]], dtype=F64), sk(th)),
            (theta[:1].clone().requires_grad_(True),))

    def test_exception(self, sk):
        with pytest.raises(ValueError, match="axis_offsets: unknown bone 'nose'"):
            CapsuleBody(sk, axis_offsets={"nose": [0, 0, 0]})
        with pytest.raises(ValueError, match=r"axis_offsets\['head_top'\]: expected 3"):
            CapsuleBody(sk, axis_offsets={"head_top": [0, 0]})
        body = CapsuleBody(sk, axis_offsets={"head_top": [0, -0.05, 0]})
        kin = sk(sk.zero_pose((2,)))
        with pytest.raises(ValueError, match="axis offsets.*Kinematics"):
            body.endpoints(kin.positions)
        with pytest.raises(ValueError, match="rotations"):
            capsule_endpoints(kin.positions, body.parent_index, body.child_index,
                              axis_offsets=body.axis_offsets)


class TestRadii:
    def test_feature_human31(self, sk):
        body = CapsuleBody(sk)
        assert body.num_bones == sk.num_joints - 1
        assert body.height == pytest.approx(1.73, abs=0.02)
        # thigh thicker than shank thicker than forearm; torso thickest; symmetric
        r = body.radius
        assert r("neck") > r("l_knee") > r("l_ankle") > r("l_wrist") > r("l_hand")
        assert r("l_knee") == r("r_knee") and r("l_elbow") == r("r_elbow")
        assert 0.07 < r("l_knee") < 0.1 and 0.08 < r("head_top") < 0.1
        # the skin ends at the head top and the toes (end sites pulled back by the radius)
        kin = sk(sk.zero_pose(dtype=F64))
        top = kin.positions[sk.joint_index("head_top")]
        assert body.skin_distance(top[None], kin).abs().item() < 1e-9
        over = CapsuleBody(sk, radii={"l_knee": 0.2})
        assert over.radius("l_knee") == 0.2 and over.radius("r_knee") == r("r_knee")

    def test_feature_scales_with_height(self, sk):
        small = CapsuleBody(sk.with_bone_lengths(scale=0.8))
        torch.testing.assert_close(small.radii, 0.8 * CapsuleBody(sk).radii, rtol=1e-6, atol=0)

    def test_exception(self, sk):
        with pytest.raises(ValueError, match="unknown bone"):
            CapsuleBody(sk, radii={"tail": 0.1})
        with pytest.raises(ValueError, match="positive radius"):
            CapsuleBody(sk, radii={"l_knee": -1.0})
        with pytest.raises(ValueError, match="height"):
            anthropometric_radii(["a"], torch.ones(1), height=0.0)

    def test_feature_unknown_names_use_length_ratio(self):
        sk2 = Skeleton.from_dict({"name": "stick", "joints": [
            {"name": "base", "parent": None, "offset": [0, 0, 0]},
            {"name": "tip", "parent": "base", "offset": [0, 0, 2.0]}]})
        body = CapsuleBody(sk2, height=2.0, shorten_end_sites=False)
        assert body.radius("tip") == pytest.approx(0.3)


class TestSurfaceSampling:
    def test_feature_points_on_surface(self, sk):
        body = CapsuleBody(sk)
        kin = sk(0.3 * torch.randn(3, sk.num_dofs, dtype=F64, generator=torch.Generator()
                                   .manual_seed(2)))
        g = torch.Generator().manual_seed(0)
        pts, nrm, bone = body.sample_surface_points(kin, 500, g)
        assert pts.shape == (3, 500, 3) and nrm.shape == (3, 500, 3) and bone.shape == (3, 500)
        per = capsule_distance(pts, body.endpoints(kin), body.radii, reduce=False)
        own = per.gather(-1, bone[..., None]).squeeze(-1)
        assert own.abs().max() < 1e-9  # on the surface of its own capsule
        assert per.min(-1).values.max() < 1e-9  # never outside the union
        torch.testing.assert_close(nrm.norm(dim=-1), torch.ones(3, 500, dtype=F64))
        # same generator seed -> same samples
        again = body.sample_surface_points(kin, 500, torch.Generator().manual_seed(0))[0]
        torch.testing.assert_close(pts, again)

    def test_feature_area_weighted(self):
        # two capsules with areas in ratio (2π·1·0.1 + 4π·0.01) : (2π·3·0.1 + 4π·0.01)
        e = torch.tensor([[[0.0, 0, 0], [0, 0, 1]], [[5.0, 0, 0], [5, 0, 3]]], dtype=F64)
        r = torch.tensor([0.1, 0.1], dtype=F64)
        _, _, bone = sample_capsule_surface(e, r, 20000, torch.Generator().manual_seed(1))
        a0, a1 = 2 * math.pi * 0.1 + 4 * math.pi * 0.01, 2 * math.pi * 0.3 + 4 * math.pi * 0.01
        assert (bone == 0).double().mean().item() == pytest.approx(a0 / (a0 + a1), abs=0.01)

    def test_feature_uniform_on_capsule(self):
        # fraction of samples on the cylinder = 2πrL / (2πrL + 4πr²)
        e, r = _unit_capsule()
        pts, nrm, _ = sample_capsule_surface(e, r, 40000, torch.Generator().manual_seed(3))
        on_cyl = (pts[:, 2] > 0) & (pts[:, 2] < 1) & (nrm[:, 2].abs() < 1e-9)
        expect = 2 * math.pi * 0.1 / (2 * math.pi * 0.1 + 4 * math.pi * 0.01)
        assert on_cyl.double().mean().item() == pytest.approx(expect, abs=0.01)
        assert pts[:, :2].mean(0).abs().max() < 0.005

    def test_feature_facing_camera(self):
        e, r = _unit_capsule()
        pts, nrm, _ = sample_capsule_surface(e, r, 2000, torch.Generator().manual_seed(4))
        cams = torch.tensor([[10.0, 0, 0.5], [-10.0, 0, 0.5]], dtype=F64)
        vis = facing_camera(pts, nrm, cams)
        assert vis.shape == (2, 2000)
        # (c - p)·n = 10 n_x - p·n: the camera at +x sees the normals with n_x > ~0.01
        assert (vis[0] == (nrm[:, 0] > 0)).double().mean() > 0.98
        assert not bool((vis[0] & vis[1]).any())  # no point faces both opposite cameras
        assert 0.45 < vis[0].double().mean().item() < 0.55


class TestMeshExport:
    @pytest.mark.parametrize("suffix", [".obj", ".glb"])
    def test_feature_export_round_trip(self, sk, tmp_path, suffix):
        body = CapsuleBody(sk)
        kin = sk(sk.zero_pose(dtype=F64))
        mesh = body.to_trimesh(kin)
        path = body.export(kin, tmp_path / f"caps{suffix}")
        loaded = trimesh.load(path, force="mesh")
        assert len(loaded.vertices) > 0 and len(loaded.faces) == len(mesh.faces)
        # vertices lie on the capsule skin (distance ~ 0 up to tessellation)
        v = torch.as_tensor(loaded.vertices, dtype=F64)
        per = capsule_distance(v, body.endpoints(kin), body.radii, reduce=False)
        assert per.abs().min(-1).values.max() < 1e-6  # each vertex on some capsule's skin
        assert body.skin_distance(v, kin).max() < 1e-6  # and never outside the union
        bounds = loaded.bounds
        assert bounds[1][2] == pytest.approx(1.75, abs=0.01)  # head top

    def test_exception(self, sk):
        body = CapsuleBody(sk)
        with pytest.raises(ValueError, match="single pose"):
            body.to_trimesh(sk(sk.zero_pose((2,))))


def test_device(device):
    sk = human31().to(device)
    body = CapsuleBody(sk).to(device)
    kin = sk(sk.zero_pose((2,), dtype=F64, device=device))
    pts = torch.randn(2, 5, 3, dtype=F64, device=device)
    assert body.skin_distance(pts, kin).device.type == device.type
    g = torch.Generator().manual_seed(0)  # a CPU generator works for data on any device
    p, _, _ = body.sample_surface_points(kin, 10, g)
    assert p.device.type == device.type
