"""Projection, distortion (kornia vs closed form), back-projection, look_at and rig factories."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.cameras import (
    CameraError,
    CameraRig,
    backproject_pixels,
    distort_normalized,
    look_at,
    make_ceiling_rig,
    make_ring_rig,
    max_monotonic_radius,
    project_points,
    project_points_planar,
)
from torchmocap.geometry import random_rotation_matrix

F64 = torch.float64


def _random_rig(C=3, dist=True, seed=0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    eyes = torch.randn(C, 3, generator=g, dtype=dtype) * 0.3 + torch.tensor([0, -4.0, 2.0],
                                                                             dtype=dtype)
    R, t = look_at(eyes, torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand(C, 3))
    f = 500 + 50 * torch.rand(C, generator=g, dtype=dtype)
    K = torch.zeros(C, 3, 3, dtype=dtype)
    K[:, 0, 0], K[:, 1, 1] = f, f * 1.01
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = 320 + torch.randn(C, generator=g, dtype=dtype), 240, 1
    d = torch.zeros(C, 5, dtype=dtype)
    if dist:
        d = torch.tensor([-0.3, 0.13, 1e-3, -5e-4, 0.0], dtype=dtype).expand(C, 5).clone()
    return CameraRig(K, R, t, (640, 480), d)


def _points(n=50, seed=1, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([0.5, 0.5, 0.6],
                                                                       dtype=dtype) + \
        torch.tensor([0.0, 0.0, 1.0], dtype=dtype)


class TestProject:
    def test_smoke(self):
        rig = _random_rig()
        pix, depth, vis = rig.project(_points())
        assert pix.shape == (3, 50, 2) and depth.shape == (3, 50) and vis.shape == (3, 50)
        assert vis.dtype == torch.bool and bool(vis.all())

    def test_cardinality(self):
        rig = _random_rig(C=2)
        pts = _points(7).expand(4, 5, 7, 3)
        pix, depth, vis = rig.project(pts)
        assert pix.shape == (4, 5, 2, 7, 2) and depth.shape == (4, 5, 2, 7)
        assert torch.allclose(pix[2, 3], rig.project(_points(7))[0])

    def test_exception(self):
        rig = _random_rig()
        with pytest.raises(ValueError, match="points"):
            rig.project(torch.zeros(5, 2, dtype=F64))
        with pytest.raises(ValueError, match="R must"):
            project_points(torch.zeros(5, 3), torch.eye(3)[None],
                           torch.eye(3)[None].repeat(2, 1, 1), torch.zeros(1, 3))
        with pytest.raises(CameraError, match="not a rotation"):
            CameraRig(rig.K, rig.R * 1.1, rig.t, (640, 480))
        with pytest.raises(CameraError, match="non-finite"):
            CameraRig(rig.K, rig.R, rig.t * float("nan"), (640, 480))
        with pytest.raises(CameraError, match="dist"):
            CameraRig(rig.K, rig.R, rig.t, (640, 480), torch.zeros(3, 4))

    def test_feature_pinhole_closed_form(self):
        rig = _random_rig(dist=False)
        pts = _points()
        pix, depth, _ = rig.project(pts)
        pc = torch.einsum("cij,nj->cni", rig.R, pts) + rig.t[:, None]
        u = rig.K[:, None, 0, 0] * pc[..., 0] / pc[..., 2] + rig.K[:, None, 0, 2]
        v = rig.K[:, None, 1, 1] * pc[..., 1] / pc[..., 2] + rig.K[:, None, 1, 2]
        torch.testing.assert_close(pix, torch.stack([u, v], -1))
        torch.testing.assert_close(depth, pc[..., 2])

    def test_feature_kornia_distortion_matches_closed_form(self):
        rig = _random_rig(dist=True)
        pts = _points()
        pix, _, _ = rig.project(pts)
        pc = torch.einsum("cij,nj->cni", rig.R, pts) + rig.t[:, None]
        xy = pc[..., :2] / pc[..., 2:]
        xyd = distort_normalized(xy, rig.dist[:, None, :].expand(3, 1, 5).squeeze(1))
        u = rig.K[:, None, 0, 0] * xyd[..., 0] + rig.K[:, None, 0, 2]
        v = rig.K[:, None, 1, 1] * xyd[..., 1] + rig.K[:, None, 1, 2]
        torch.testing.assert_close(pix, torch.stack([u, v], -1))
        # distortion really changes the pixels (k1 = -0.3 pulls points towards the centre)
        assert (pix - rig.project(pts, distort=False)[0]).abs().max() > 5

    def test_feature_visibility(self):
        rig = make_ring_rig(1, radius=4.0, height=1.0, target=(0, 0, 1), image_size=(320, 240))
        pts = torch.tensor([[0.0, 0.0, 1.0],     # centre: visible
                            [0.0, -6.0, 1.0],    # behind the camera (camera at y=-4)
                            [5.0, 0.0, 1.0],     # far outside the 60 deg FOV
                            [0.0, 0.0, 1.5]], dtype=F64)
        pix, depth, vis = rig.project(pts)
        assert vis[0].tolist() == [True, False, False, True]
        assert depth[0, 1] < 0
        torch.testing.assert_close(pix[0, 0], torch.tensor([159.5, 119.5], dtype=F64))
        assert pix[0, 3, 1] < 119.5  # higher point appears higher in the image (v down)

    def test_feature_fold_back_guard(self):
        # a strong barrel lens folds back beyond r ~ 1.29: a far-off-axis point would land inside
        d = torch.tensor([[-0.2, 0.0, 0.0, 0.0, 0.0]], dtype=F64)
        rmax = max_monotonic_radius(d)
        assert rmax.item() == pytest.approx(1 / math.sqrt(0.6), abs=2e-3)
        K = torch.tensor([[[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]], dtype=F64)
        pts = torch.tensor([[2.0, 0.0, 1.0]], dtype=F64)  # r = 2 beyond the fold
        pix, _, vis = project_points(pts, K, torch.eye(3, dtype=F64)[None],
                                     torch.zeros(1, 3, dtype=F64), d,
                                     torch.tensor([[320, 240]]))
        assert not bool(vis[0, 0])

    def test_feature_far_points_stay_finite(self):
        """Behind a distorting lens (or far off axis) a point is distorted from the monotonic
        radius along its direction: finite pixels and gradients in float32, flagged invisible,
        and the same pixel as the point at that radius."""
        d = torch.tensor([[-0.2, 0.05, 0.001, -0.002, 0.01]])
        K = torch.tensor([[[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]])
        R, t, size = torch.eye(3)[None], torch.zeros(1, 3), torch.tensor([[320, 240]])
        pts = torch.tensor([[0.5, 0.2, -1.0], [40.0, 0.0, 1.0], [0.1, 0.0, 1.0]],
                           requires_grad=True)
        pix, _, vis = project_points(pts, K, R, t, d, size)
        assert bool(torch.isfinite(pix).all()) and vis[0].tolist() == [False, False, True]
        pix.sum().backward()
        assert bool(torch.isfinite(pts.grad).all())
        r = float(max_monotonic_radius(d.double()))
        edge = project_points(torch.tensor([[r, 0.0, 1.0]]), K, R, t, d, size)[0]
        torch.testing.assert_close(pix[0, 1], edge[0, 0], atol=0.05, rtol=0)
        # inside the radius nothing changes
        near = project_points(pts[2:].detach().double(), K.double(), R.double(),
                              t.double(), d.double())[0]
        torch.testing.assert_close(pix[0, 2].double(), near[0, 0], atol=1e-3, rtol=0)

    def test_gradcheck(self):
        rig = _random_rig(C=2, dist=True)
        pts = _points(4).requires_grad_(True)
        assert torch.autograd.gradcheck(lambda p: rig.project(p)[0], (pts,))

    def test_gradcheck_camera_parameters(self):
        """Pixels are differentiable in K, R (through its rotation vector: R stays a rotation),
        t and the distortion; float64, tiny case."""
        from torchmocap.geometry import so3_exp

        rig = _random_rig(C=2, dist=True)
        pts = _points(3)
        K = rig.K.clone().requires_grad_()
        t = rig.t.clone().requires_grad_()
        d = rig.dist.clone().requires_grad_()
        w = torch.tensor([[0.01, -0.02, 0.03], [0.0, 0.02, -0.01]], dtype=F64,
                         requires_grad=True)
        size = rig.image_size

        def pix(K, w, t, d):
            return project_points(pts, K, so3_exp(w) @ rig.R, t, d, size)[0]

        assert torch.autograd.gradcheck(pix, (K, w, t, d))
        # the module's buffers carry the same gradients (a calibration refinement use)
        R = rig.R.clone().requires_grad_()
        assert torch.autograd.gradcheck(
            lambda K, R, t: project_points(pts, K, R, t, None, size)[0], (K, R, t))

    @pytest.mark.parametrize("dist", [False, True])
    def test_feature_planar_matches_project(self, dist):
        rig = make_ring_rig(3, image_size=(320, 240)).double() if not dist else _random_rig()
        pts = torch.cat([_points(), torch.tensor([[0.0, -30.0, 1.0]], dtype=F64)])  # + behind
        pix, depth, vis = rig.project(pts)
        u, v, z, ok = rig.project_planar(pts)
        assert u.shape == (rig.num_cameras, pts.shape[0])
        torch.testing.assert_close(torch.stack([u, v], -1)[vis], pix[vis])
        torch.testing.assert_close(z, depth)
        assert torch.equal(ok, vis) and not bool(vis.all())
        fn = project_points_planar(pts, rig.K, rig.R, rig.t, rig.dist, rig.image_size)
        torch.testing.assert_close(fn[1], v)
        with pytest.raises(ValueError, match="points"):
            rig.project_planar(pts[None])

    @pytest.mark.parametrize("dist", [False, True])
    def test_planar_without_visibility_same_pixels(self, dist):
        rig = _random_rig(dist=dist).float()
        pts = _points(400).float()
        u, v, z, ok = rig.project_planar(pts)
        u2, v2, z2, none = rig.project_planar(pts, visibility=False)
        assert none is None and ok is not None
        assert torch.equal(u, u2) and torch.equal(v, v2) and torch.equal(z, z2)
        # the planar lens model against the stacked (kornia) one, in float32
        pix = rig.project(pts)[0]
        torch.testing.assert_close(torch.stack([u, v], -1), pix, atol=2e-3, rtol=0)

    def test_planar_beyond_the_monotonic_radius_as_project(self):
        """Points far off the optical axis (beyond k1 < 0's fold, where the polynomial would
        bring them back into the image) get project_points' pixels on the planar path too,
        visibility or not, and stay outside the image."""
        rig = _random_rig(dist=True)
        g = torch.Generator().manual_seed(3)
        # points 1 m in front of each camera's plane, 1-6 m sideways: normalised radius 1-6
        side = torch.rand(40, 1, generator=g, dtype=F64) * 5 + 1
        ang = torch.rand(40, 1, generator=g, dtype=F64) * 2 * torch.pi
        xc = torch.cat([side * ang.cos(), side * ang.sin(), torch.ones(40, 1, dtype=F64)], 1)
        pts = (xc - rig.t[0]) @ rig.R[0]  # camera 0's frame to the world
        pix, _, vis = rig.project(pts)
        for visibility in (True, False):
            u, v, _, _ = rig.project_planar(pts, visibility=visibility)
            assert torch.equal(torch.stack([u, v], -1), pix)
        assert not bool(vis[0].any())
        inside = (pix[0, :, 0] >= 0) & (pix[0, :, 0] < 640) & (pix[0, :, 1] >= 0) & \
            (pix[0, :, 1] < 480)
        assert not bool(inside.any())

    def test_module(self):
        rig = _random_rig()
        pts = _points()
        pix = project_points(pts, rig.K, rig.R, rig.t, rig.dist, rig.image_size)[0]
        torch.testing.assert_close(rig(pts), pix)
        rig32 = rig.to(torch.float32)
        assert rig32.K.dtype == torch.float32 and rig32(pts.float()).dtype == torch.float32
        torch.testing.assert_close(rig32(pts.float()).double(), pix, atol=1e-2, rtol=0)


class TestBackproject:
    def test_feature_round_trip(self):
        rig = _random_rig(dist=True)
        pts = _points(30)
        pix, depth, _ = rig.project(pts)
        o, d = rig.backproject(pix)
        assert o.shape == (3, 30, 3) and d.shape == (3, 30, 3)
        torch.testing.assert_close(d.norm(dim=-1), torch.ones(3, 30, dtype=F64))
        # the ray passes through the original point
        v = pts[None] - o
        s = (v * d).sum(-1, keepdim=True)
        assert (v - s * d).norm(dim=-1).max() < 1e-7
        assert bool((s > 0).all())
        torch.testing.assert_close(o[:, 0], rig.camera_centers())

    def test_feature_kornia_undistort_converges(self):
        # kornia's default 5 iterations leave ~1e-2 px at the corners; 20 is exact enough
        rig = _random_rig(C=1, dist=True)
        u, v = torch.meshgrid(torch.linspace(0, 639, 9, dtype=F64),
                              torch.linspace(0, 479, 7, dtype=F64), indexing="ij")
        pix = torch.stack([u, v], -1).reshape(1, -1, 2)
        o, d = rig.backproject(pix)
        back = rig.project(o + 2.0 * d)[0]
        assert (back - pix).abs().max() < 1e-6

    def test_cardinality(self):
        rig = _random_rig(C=2)
        o, d = backproject_pixels(torch.rand(5, 2, 4, 2, dtype=F64) * 300, rig.K, rig.R, rig.t,
                                  rig.dist)
        assert o.shape == d.shape == (5, 2, 4, 3)

    def test_exception(self):
        rig = _random_rig(C=2)
        with pytest.raises(ValueError, match="one set per camera"):
            rig.backproject(torch.zeros(3, 4, 2, dtype=F64))


class TestLookAtAndRigs:
    def test_feature_look_at(self):
        eye = torch.tensor([1.0, -3.0, 2.0], dtype=F64)
        tgt = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
        R, t = look_at(eye, tgt)
        torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=F64))
        assert torch.linalg.det(R).item() == pytest.approx(1.0)
        torch.testing.assert_close(R @ eye + t, torch.zeros(3, dtype=F64))
        z = (tgt - eye) / (tgt - eye).norm()
        torch.testing.assert_close(R[2], z)
        assert R[1] @ torch.tensor([0.0, 0, 1], dtype=F64) < 0  # image y points down
        with pytest.raises(ValueError, match="parallel"):
            look_at(torch.tensor([0.0, 0, 3]), torch.tensor([0.0, 0, 0]))

    @pytest.mark.parametrize("size", [(320, 240), (640, 480), (100, 300)])
    def test_feature_ring(self, size):
        rig = make_ring_rig(4, radius=4.0, height=2.5, target=(0, 0, 1), image_size=size)
        c = rig.camera_centers()
        torch.testing.assert_close(c[:, :2].norm(dim=-1), torch.full((4,), 4.0, dtype=F64))
        torch.testing.assert_close(c[:, 2], torch.full((4,), 2.5, dtype=F64))
        # first camera on the -y side, facing +y (sees the front of human31)
        assert c[0, 1] < -3.9 and rig.optical_axes()[0, 1] > 0.9
        # target projects to the image centre; horizontal FOV is 60 degrees
        pix, _, vis = rig.project(torch.tensor([[0.0, 0.0, 1.0]], dtype=F64))
        w, h = size
        torch.testing.assert_close(pix[:, 0], torch.tensor([[(w - 1) / 2, (h - 1) / 2]] * 4,
                                                           dtype=F64))
        fov = 2 * math.degrees(math.atan(0.5 * w / rig.K[0, 0, 0].item()))
        assert fov == pytest.approx(60.0)
        # a standing 1.8 m person at the centre is fully in view of every camera
        body = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.8], [0.4, 0.0, 1.0]], dtype=F64)
        assert bool(rig.project(body)[2].all())

    def test_feature_ceiling(self):
        rig = make_ceiling_rig(4)
        c = rig.camera_centers()
        assert torch.allclose(c[:, 2], torch.full((4,), 3.0, dtype=F64))
        assert bool((rig.optical_axes()[:, 2] < 0).all())
        body = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.8]], dtype=F64)
        assert bool(rig.project(body)[2].all())

    def test_feature_subset_and_scale(self):
        rig = make_ring_rig(4)
        sub = rig.subset([2, 0])
        assert sub.names == ["ring2", "ring0"]
        torch.testing.assert_close(sub.R, rig.R[[2, 0]])
        big = rig.scaled_images(2.0)
        p = torch.tensor([[0.3, 0.1, 1.2]], dtype=F64)
        torch.testing.assert_close(big(p) + 0.5, 2 * (rig(p) + 0.5))
        assert big.image_size[0].tolist() == [640, 480]

    def test_exception(self):
        with pytest.raises(CameraError, match="fov_deg"):
            make_ring_rig(4, fov_deg=200)
        with pytest.raises(CameraError, match="num"):
            make_ring_rig(0)

    @pytest.mark.parametrize("factory", [make_ring_rig, make_ceiling_rig])
    @pytest.mark.parametrize("kw, field", [
        ({"image_size": (0, 240)}, "image_size"), ({"image_size": (320, -240)}, "image_size"),
        ({"image_size": (320.5, 240)}, "image_size"), ({"image_size": (320,)}, "image_size"),
        ({"image_size": (float("inf"), 240)}, "image_size"),
        ({"fov_deg": float("nan")}, "fov_deg"), ({"fov_deg": 0.0}, "fov_deg"),
        ({"num": 2.5}, "num"), ({"num": True}, "num"), ({"height": float("inf")}, "height"),
        ({"target": (0.0, float("nan"), 1.0)}, "target"), ({"target": (0.0, 1.0)}, "target"),
    ])
    def test_exception_factory_fields(self, factory, kw, field):
        with pytest.raises(CameraError, match=rf"^{field}: "):
            factory(**kw)

    def test_exception_factory_distances(self):
        for bad in (0.0, -1.0, float("nan"), float("inf")):
            with pytest.raises(CameraError, match="^radius: "):
                make_ring_rig(radius=bad)
            with pytest.raises(CameraError, match="^half_width: "):
                make_ceiling_rig(half_width=bad)


class TestRigValidation:
    """CameraRig rejects focal lengths and image sizes a pinhole camera cannot have (before:
    fx = 0 was accepted and back-projection failed later in a linear solve)."""

    @pytest.mark.parametrize("fx, fy", [(0.0, 500.0), (500.0, 0.0), (-500.0, 500.0),
                                        (500.0, -1e-3)])
    def test_exception_focal_lengths(self, fx, fy):
        rig = _random_rig(C=2)
        K = rig.K.clone()
        K[1, 0, 0], K[1, 1, 1] = fx, fy
        with pytest.raises(CameraError, match=r"K: focal lengths .* camera 1 .*fx"):
            CameraRig(K, rig.R, rig.t, (640, 480))

    @pytest.mark.parametrize("size", [(0, 480), (640, -480), [[640, 480], [640, 0]],
                                      (640.5, 480.0), (float("nan"), 480.0),
                                      (float("inf"), 480.0), (640, 480, 3), "640x480"])
    def test_exception_image_size(self, size):
        rig = _random_rig(C=2)
        with pytest.raises(CameraError, match="^image_size: "):
            CameraRig(rig.K, rig.R, rig.t, size)

    def test_feature_integral_float_sizes_accepted(self):
        rig = _random_rig(C=2)
        r2 = CameraRig(rig.K, rig.R, rig.t, (640.0, 480.0))
        assert r2.image_size.dtype == torch.int64 and r2.image_size[1].tolist() == [640, 480]

    def test_exception_calibration_files(self, tmp_path):
        from torchmocap.cameras import read_rig, rig_to_dict, write_rig

        rig = _random_rig(C=2)
        data = rig_to_dict(rig)
        data["cameras"][1]["camera_matrix"][0][0] = 0.0
        import json

        (tmp_path / "r.json").write_text(json.dumps(data))
        with pytest.raises(CameraError, match=r"r.json: K: focal lengths"):
            read_rig(tmp_path / "r.json")
        data = rig_to_dict(rig)
        data["cameras"][0]["image_width"] = 640.5
        (tmp_path / "w.json").write_text(json.dumps(data))
        with pytest.raises(CameraError, match=r"w.json: camera 0: image_width"):
            read_rig(tmp_path / "w.json")
        write_rig(rig, tmp_path / "ok.yaml")
        assert read_rig(tmp_path / "ok.yaml").num_cameras == 2


def test_rotation_helper_is_used_consistently():
    # a rig built from random rotations projects like the explicit formula
    g = torch.Generator().manual_seed(3)
    R = random_rotation_matrix((2,), generator=g, dtype=F64)
    t = torch.tensor([[0.0, 0, 5], [0.1, 0, 4]], dtype=F64)
    K = torch.tensor([[500.0, 0, 100], [0, 500, 100], [0, 0, 1]], dtype=F64).expand(2, 3, 3)
    rig = CameraRig(K, R, t, (200, 200))
    p = torch.randn(6, 3, generator=g, dtype=F64) * 0.2
    pc = torch.einsum("cij,nj->cni", R, p) + t[:, None]
    torch.testing.assert_close(rig(p), 500 * pc[..., :2] / pc[..., 2:] + 100)


def test_device(device):
    rig = _random_rig().to(device)
    pts = _points().to(device)
    pix, depth, vis = rig.project(pts)
    assert pix.device.type == device.type and vis.device.type == device.type
    o, d = rig.backproject(pix)
    torch.testing.assert_close(o[:, 0].cpu(), rig.camera_centers().cpu())
