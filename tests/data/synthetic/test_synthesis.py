"""Observation synthesis: rasteriser vs brute force, skinned vs capsule masks, depth on the mesh,
determinism, and clear errors."""

from __future__ import annotations

import copy

import pytest
import torch

from torchmocap.cameras import CameraRig, look_at
from torchmocap.data import SensorPlacementError
from torchmocap.data.subjects.mocap import fit_subject
from torchmocap.data.synthetic import (
    CameraVisibilityError,
    ScenarioError,
    SynthesisError,
    build_rig,
    load_scenario,
    synthesize,
)
from torchmocap.data.synthetic.render import (
    capsule_mesh,
    face_normals,
    rasterize_mask,
    rasterize_zbuffer,
    vertex_normals,
)
from torchmocap.data.synthetic.synthesis import body_surface, render_silhouettes, subgenerator
from torchmocap.io import bundled_clip_path, load_motion

SMALL = {"image_size": [160, 120]}


@pytest.fixture(scope="module")
def clip():
    return load_motion(bundled_clip_path()).resample(25)


@pytest.fixture(scope="module")
def subject(clip):
    return fit_subject(clip.slice(0, 4))


def _brute_force(pix: torch.Tensor, depth: torch.Tensor, faces: torch.Tensor, W: int, H: int):
    """Every pixel centre against every triangle (float64): coverage and nearest depth."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    p = torch.stack([xs, ys], -1).reshape(-1, 1, 2)
    tri = pix[faces].double()  # (F, 3, 2)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    def cross(o, u, q):
        return (u[..., 0] - o[..., 0]) * (q[..., 1] - o[..., 1]) - \
            (u[..., 1] - o[..., 1]) * (q[..., 0] - o[..., 0])

    area = cross(a, b, c)
    l0 = cross(b, c, p) / area
    l1 = cross(c, a, p) / area
    l2 = cross(a, b, p) / area
    inside = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
    z = depth[faces].double()
    zp = 1 / (l0 / z[:, 0] + l1 / z[:, 1] + l2 / z[:, 2])
    zp = torch.where(inside, zp, torch.full_like(zp, float("inf")))
    return inside.any(-1).reshape(H, W), zp.amin(-1).reshape(H, W)


class TestRasterizer:
    def test_smoke(self):
        pix = torch.tensor([[[1.0, 1.0], [8.0, 1.0], [1.0, 8.0]]])
        m = rasterize_mask(pix, torch.ones(1, 3), torch.tensor([[0, 1, 2]]), 10, 10)
        assert m.shape == (1, 10, 10) and m.dtype == torch.bool
        assert int(m.sum()) == 36  # pixel centres with x, y >= 1 and x + y <= 9

    def test_feature_vs_brute_force(self):
        g = torch.Generator().manual_seed(0)
        W, H, V, F = 48, 36, 30, 25
        pix = torch.rand(V, 2, generator=g, dtype=torch.float64) * torch.tensor([60.0, 46]) - 6
        depth = 1 + 4 * torch.rand(V, generator=g, dtype=torch.float64)
        faces = torch.randint(0, V, (F, 3), generator=g)
        faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                      & (faces[:, 0] != faces[:, 2])]
        cov, zref = _brute_force(pix, depth, faces, W, H)
        m = rasterize_mask(pix[None], depth[None], faces, W, H)[0]
        assert torch.equal(m, cov)
        zb = rasterize_zbuffer(pix[None], depth[None], faces, W, H, budget=500)
        assert torch.equal(zb.mask[0], cov)
        assert torch.allclose(zb.depth[0][cov], zref[cov], atol=1e-9)
        assert bool(torch.isinf(zb.depth[0][~cov]).all()) and bool((zb.face[0][~cov] == -1).all())
        # barycentrics are a partition of unity at every covered pixel
        assert torch.allclose(zb.bary[0][cov].sum(-1), torch.ones(int(cov.sum()),
                                                                   dtype=torch.float64))

    def test_gap_between_limbs(self):
        # two parallel bars 3 px apart: the gap stays empty, the bars are filled
        quads = [[2.0, 2.0, 10.0, 30.0], [14.0, 2.0, 22.0, 30.0]]
        pts, faces = [], []
        for x0, y0, x1, y1 in quads:
            k = len(pts)
            pts += [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
            faces += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
        pix = torch.tensor(pts)[None]
        m = rasterize_mask(pix, torch.ones(1, len(pts)), torch.tensor(faces), 32, 32)[0]
        assert int(m.sum()) == 2 * 9 * 29
        assert not bool(m[:, 11:14].any())
        assert bool(m[2:31, 2:11].all()) and bool(m[2:31, 14:23].all())

    def test_behind_camera_skipped(self):
        pix = torch.tensor([[[1.0, 1.0], [8.0, 1.0], [1.0, 8.0]]])
        m = rasterize_mask(pix, torch.tensor([[1.0, -1.0, 1.0]]), torch.tensor([[0, 1, 2]]), 10,
                           10)
        assert int(m.sum()) == 0

    def test_exception(self):
        with pytest.raises(ValueError, match="pixels"):
            rasterize_mask(torch.zeros(3, 2), torch.zeros(3), torch.zeros(1, 3).long(), 4, 4)
        with pytest.raises(ValueError, match="depth"):
            rasterize_mask(torch.zeros(1, 3, 2), torch.zeros(1, 4), torch.zeros(1, 3).long(), 4,
                           4)
        with pytest.raises(ValueError, match="faces"):
            rasterize_zbuffer(torch.zeros(1, 3, 2), torch.zeros(1, 3), torch.zeros(3).long(), 4,
                              4)

    def test_capsule_mesh_closed_and_normals(self):
        ep = torch.tensor([[[0.0, 0, 0], [0, 0, 1.0]], [[1.0, 0, 0], [2.0, 0, 0]]],
                          dtype=torch.float64)
        r = torch.tensor([0.2, 0.1], dtype=torch.float64)
        v, f, fc = capsule_mesh(ep, r, sections=16, rings=4)
        assert f.shape[0] == fc.shape[0] and int(fc.max()) == 1
        # every vertex is at distance r from its capsule's axis segment
        from torchmocap.body import capsule_distance

        d = capsule_distance(v[None], ep[None], r)[0]
        assert d.abs().max() < 1e-9
        # the vertex normal of a sphere-swept surface points away from the axis
        n = vertex_normals(v, f)
        k = v.shape[0] // 2
        axis_pt = torch.stack([torch.zeros(k), torch.zeros(k), v[:k, 2].clamp(0, 1)], -1)
        radial = torch.nn.functional.normalize(v[:k] - axis_pt.double(), dim=-1)
        assert ((n[:k] * radial).sum(-1).abs() > 0.9).float().mean() > 0.95
        assert face_normals(v, f).shape == (f.shape[0], 3)


def _iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a & b).sum((-1, -2)).float() / (a | b).sum((-1, -2)).float()


class TestSilhouettes:
    def test_skinned_vs_capsules_iou(self, subject):
        sk = copy.deepcopy(subject.skeleton).float()
        theta = subject.theta.float()[:2].clone()
        theta[:, :2] -= subject.positions[:2, 0, :2].float().mean(0)
        rig = build_rig("ring4", [320, 240]).float()
        skin = render_silhouettes(body_surface(sk, theta, "skinned"), rig)
        caps = render_silhouettes(body_surface(sk, theta, "capsules"), rig)
        iou = _iou(skin, caps)
        assert bool((skin.sum((-1, -2)) > 500).all())
        assert float(iou.min()) > 0.7, iou
        assert float(iou.max()) < 0.98, iou

    def test_masks_match_projected_joints(self, subject):
        sc = load_scenario("clean", **SMALL, images={"enabled": False}, depth={"enabled": False},
                           imu={"enabled": False})
        seq = synthesize(subject, sc, seed=0, frames=2)
        pix, _, vis = seq.rig.project(seq.ground_truth.positions.float())
        names = seq.ground_truth.joint_names
        # trunk joints project inside the silhouette in every view
        for j in ("pelvis", "spine", "neck", "l_hip", "r_hip"):
            uv = pix[:, :, names.index(j)].round().long()
            t = torch.arange(2)[:, None].expand(2, 4)
            c = torch.arange(4)[None].expand(2, 4)
            assert bool(seq.silhouettes[t, c, uv[..., 1], uv[..., 0]].all()), j


class TestSynthesize:
    def test_smoke_and_determinism(self, subject):
        sc = load_scenario("outdoor", **SMALL)
        a = synthesize(subject, sc, seed=3, frames=3)
        b = synthesize(subject, sc, seed=3, frames=3)
        c = synthesize(subject, sc, seed=4, frames=3)
        assert a.modalities == ["silhouettes", "images", "imu", "depth", "joints2d",
                                "ground_truth", "rig"]
        assert a.silhouettes.shape == (3, 4, 120, 160) and a.images.shape == (3, 4, 120, 160, 3)
        assert a.images.dtype == torch.uint8 and a.joints2d.shape == (3, 4, 21, 3)
        for x, y in ((a.silhouettes, b.silhouettes), (a.images, b.images),
                     (a.imu.quaternions, b.imu.quaternions), (a.depth.points, b.depth.points),
                     (a.joints2d, b.joints2d), (a.view_dropped, b.view_dropped)):
            assert torch.equal(x, y)
        assert not torch.equal(a.images, c.images)
        assert not torch.equal(a.imu.quaternions, c.imu.quaternions)
        # rendering in other chunks gives the same sequence
        f = synthesize(subject, sc, seed=3, frames=3, chunk_frames=1)
        assert torch.equal(a.images, f.images) and torch.equal(a.silhouettes, f.silhouettes)
        # a generator is an alternative source of the seed
        g1, g2 = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
        d = synthesize(subject, sc, generator=g1, frames=2)
        e = synthesize(subject, sc, generator=g2, frames=2)
        assert torch.equal(d.silhouettes, e.silhouettes)

    def test_modalities_have_independent_streams(self, subject):
        sc = load_scenario("studio", **SMALL)
        a = synthesize(subject, sc, seed=5, frames=2)
        off = load_scenario("studio", **SMALL, images={"enabled": False},
                            depth={"enabled": False})
        b = synthesize(subject, off, seed=5, frames=2)
        assert b.images is None and b.depth is None
        assert torch.equal(a.silhouettes, b.silhouettes)
        assert torch.equal(a.imu.quaternions, b.imu.quaternions)
        assert torch.equal(a.joints2d, b.joints2d)
        assert subgenerator(1, "imu").initial_seed() != subgenerator(1, "depth").initial_seed()

    def test_from_clip_and_recentering(self, clip):
        seq = synthesize(clip.slice(0, 10), load_scenario("clean", **SMALL, fps=12.5), seed=0)
        assert seq.fps == 12.5 and seq.num_frames == 5  # 10 frames at 25 fps -> 5 at 12.5 fps
        gt = seq.ground_truth
        pel = gt.positions[:, gt.joint_names.index("pelvis"), :2].mean(0)
        assert pel.abs().max() < 1e-9
        # ground truth stays consistent: FK of the (shifted) fitted poses ≈ exact joints
        sk = gt.build_skeleton()
        err = (sk.joint_positions(gt.theta) - gt.positions).norm(dim=-1).mean()
        assert err < 0.05

    def test_depth_points_on_mesh(self, subject):
        sc = load_scenario("clean", **SMALL, silhouettes={"enabled": False},
                           images={"enabled": False}, joints2d={"enabled": False},
                           imu={"enabled": False}, recenter=False)
        seq = synthesize(subject, sc, seed=0, frames=1)
        pts = seq.depth.frame_points(0).double()
        assert pts.shape[0] > 200
        sk = copy.deepcopy(subject.skeleton).float()
        surf = body_surface(sk, subject.theta[:1].float(), "skinned")
        d = _point_mesh_distance(pts[::4], surf.vertices[0].double(), surf.faces)
        assert float(d.max()) < 1e-4, float(d.max())
        # noisy depth moves points off the surface by about the configured std
        noisy = load_scenario("clean", **SMALL, silhouettes={"enabled": False},
                              images={"enabled": False}, joints2d={"enabled": False},
                              imu={"enabled": False}, recenter=False,
                              depth={"noise_std": 0.01})
        seq2 = synthesize(subject, noisy, seed=0, frames=1)
        assert torch.equal(seq2.depth.counts, seq.depth.counts)
        shift = (seq2.depth.frame_points(0) - seq.depth.frame_points(0)).norm(dim=-1)
        z = 3.2  # ≈ camera-to-body distance
        assert 0.3 * 0.01 * z * z < float(shift.median()) < 3 * 0.01 * z * z

    def test_depth_holes_and_cap(self, subject):
        base = dict(SMALL, silhouettes={"enabled": False}, images={"enabled": False},
                    joints2d={"enabled": False}, imu={"enabled": False})
        full = synthesize(subject, load_scenario("clean", **base), seed=0, frames=2)
        holes = synthesize(subject, load_scenario("clean", **base, depth={"hole_prob": 0.5}),
                           seed=0, frames=2)
        ratio = holes.depth.counts.double() / full.depth.counts.double()
        assert bool(((ratio > 0.4) & (ratio < 0.6)).all())
        cap = synthesize(subject, load_scenario("clean", **base, depth={"max_points": 100}),
                         seed=0, frames=2)
        assert cap.depth.points.shape == (2, 100, 3) and bool((cap.depth.counts == 100).all())

    def test_capsule_body_pipeline(self, subject):
        sc = load_scenario("studio", image_size=[80, 60], body="capsules")
        seq = synthesize(subject, sc, seed=0, frames=1)
        assert seq.meta.body == "capsules"
        assert int(seq.silhouettes[0].sum()) > 4 * 40 and int(seq.depth.counts[0]) > 100
        assert int(seq.images[0][seq.silhouettes[0]].float().std()) > 5
        sk = copy.deepcopy(subject.skeleton).float()
        surf = body_surface(sk, subject.theta[:1].float(), "capsules")
        # every capsule face is carried by the parent joint of its bone
        names = surf.part_names
        assert {names[i] for i in surf.face_part.unique().tolist()} == {
            names[p] for p in set(sk.parents) if p >= 0}

    def test_exception(self, subject, clip):
        with pytest.raises(SynthesisError, match="frames"):
            synthesize(subject, "clean", frames=0)
        with pytest.raises(SynthesisError, match="clip_or_subject"):
            synthesize("walk.bvh", "clean")
        with pytest.raises(ValueError, match="empty"):
            synthesize(clip.slice(5, 5), "clean")
        with pytest.raises(SensorPlacementError, match="wing"):
            synthesize(subject, load_scenario("clean", **SMALL, imu={"sensors": {"x": "wing"},
                                                                     "tracking": []}), frames=1)
        with pytest.raises(SynthesisError, match="body"):
            body_surface(subject.skeleton, subject.theta[:1], "voxels")
        with pytest.raises(ScenarioError, match="body"):
            load_scenario("clean", body="voxels")

    def test_rig_looking_away(self, subject):
        eye = torch.tensor([[0.0, -4.0, 1.5]], dtype=torch.float64)
        R, t = look_at(eye, torch.tensor([[0.0, -10.0, 1.5]], dtype=torch.float64))
        K = torch.tensor([[[100.0, 0, 79.5], [0, 100, 59.5], [0, 0, 1]]], dtype=torch.float64)
        good = build_rig("ring4", [160, 120])
        rig = CameraRig(torch.cat([good.K, K]), torch.cat([good.R, R]), torch.cat([good.t, t]),
                        (160, 120), names=good.names + ["away"])
        with pytest.raises(CameraVisibilityError, match="away"):
            synthesize(subject, load_scenario("clean", **SMALL, rig=_rig_dict(rig)), frames=1)
        with pytest.raises(CameraVisibilityError, match="depth0"):
            synthesize(subject, load_scenario("clean", **SMALL, depth={"target": [0, -10, 1.0]},
                                              silhouettes={"enabled": False},
                                              images={"enabled": False},
                                              joints2d={"enabled": False}), frames=1)


def _rig_dict(rig):
    from torchmocap.cameras import rig_to_dict

    return rig_to_dict(rig)


def _point_mesh_distance(p: torch.Tensor, v: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Exact distance ``(N,)`` from points to a triangle mesh (plane if the projection is inside
    the triangle, else the nearest edge segment), by brute force over all faces."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]  # (F, 3)
    n = torch.linalg.cross(b - a, c - a)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-15)
    out = torch.full((p.shape[0],), float("inf"), dtype=p.dtype)
    for i in range(0, p.shape[0], 64):
        q = p[i:i + 64, None]  # (n, 1, 3)
        dist_plane = ((q - a) * n).sum(-1)
        proj = q - dist_plane[..., None] * n

        inside = torch.ones_like(dist_plane, dtype=torch.bool)
        for u, w in ((a, b), (b, c), (c, a)):
            side = (torch.linalg.cross((w - u).expand_as(proj), proj - u) * n).sum(-1)
            inside &= side >= 0
        d = torch.where(inside, dist_plane.abs(), torch.full_like(dist_plane, float("inf")))
        for u, w in ((a, b), (b, c), (c, a)):
            e = w - u
            s = (((q - u) * e).sum(-1) / (e * e).sum(-1).clamp_min(1e-15)).clamp(0, 1)
            d = torch.minimum(d, (q - (u + s[..., None] * e)).norm(dim=-1))
        out[i:i + 64] = d.amin(-1)
    return out
