"""MotionClip: angle decomposition, FK through the core Skeleton, resample, slice, from_skeleton."""

from __future__ import annotations

import itertools
import math
import warnings

import pytest
import torch

from torchmocap.geometry import axis_angle_rotation, geodesic_angle
from torchmocap.io import MotionClip, read_bvh, write_bvh
from torchmocap.io._euler import angles_to_matrix, matrix_to_angles
from torchmocap.io.motion import Y_UP_TO_Z_UP, y_up_to_z_up, z_up_to_y_up
from torchmocap.skeleton import Skeleton, human31


def _naive_fk(clip: MotionClip) -> torch.Tensor:
    """Independent oracle: textbook recursive FK straight from the clip's fields."""
    J = clip.num_joints
    off = clip.frame_offsets()
    R = [None] * J
    p = [None] * J
    for j in range(J):
        if clip.parents[j] < 0:
            R[j] = clip.rotations[:, j]
            p[j] = clip.offsets[j] + clip.root_translation
        else:
            q = clip.parents[j]
            p[j] = p[q] + (R[q] @ off[:, j, :, None])[..., 0]
            R[j] = R[q] @ clip.rotations[:, j]
    return torch.stack(p, 1)


def _random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    w = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    w = w / w.norm(dim=-1, keepdim=True) * torch.rand(n, 1, generator=gen, dtype=torch.float64) * 3
    return axis_angle_rotation(w / w.norm(dim=-1, keepdim=True), w.norm(dim=-1))


class TestEulerDecomposition:
    @pytest.mark.parametrize("perm", list(itertools.permutations(range(3))))
    def test_feature_all_bvh_orders_exact(self, perm):
        gen = torch.Generator().manual_seed(0)
        axes = torch.eye(3, dtype=torch.float64)[list(perm)]
        R = _random_rotations(500, gen)
        ang = matrix_to_angles(R, axes)
        assert (angles_to_matrix(ang, axes) - R).abs().max() < 1e-12

    def test_feature_rotated_axes_and_reflection(self):
        # ASF axes are the columns of a pre-rotation C (any order): still exact
        gen = torch.Generator().manual_seed(1)
        C = _random_rotations(1, gen)[0]
        for perm in ([2, 1, 0], [0, 2, 1]):  # det +1 / -1 arrangements
            axes = C.T[perm]
            R = _random_rotations(200, gen)
            assert (angles_to_matrix(matrix_to_angles(R, axes), axes) - R).abs().max() < 1e-12

    def test_feature_recovers_angles_and_gimbal(self):
        axes = torch.eye(3, dtype=torch.float64)[[2, 0, 1]]  # Zrotation Xrotation Yrotation
        a = torch.tensor([[0.3, -0.7, 1.1], [0.4, math.pi / 2, -0.2], [0.1, -math.pi / 2, 0.5]],
                         dtype=torch.float64)
        R = angles_to_matrix(a, axes)
        b = matrix_to_angles(R, axes)
        assert torch.allclose(b[0], a[0], atol=1e-12)
        assert (angles_to_matrix(b, axes) - R).abs().max() < 1e-12  # gimbal rows too

    @pytest.mark.parametrize("k", [1, 2])
    def test_feature_fewer_axes(self, k):
        gen = torch.Generator().manual_seed(2)
        C = _random_rotations(1, gen)[0]
        axes = C.T[:k]
        a = (torch.rand(100, k, generator=gen, dtype=torch.float64) - 0.5) * 5
        R = angles_to_matrix(a, axes)
        assert (angles_to_matrix(matrix_to_angles(R, axes), axes) - R).abs().max() < 1e-12

    def test_exception_non_orthonormal(self):
        axes = torch.tensor([[1.0, 0, 0], [0.6, 0.8, 0]], dtype=torch.float64)
        with pytest.raises(ValueError, match="orthonormal"):
            matrix_to_angles(torch.eye(3, dtype=torch.float64), axes)


def test_y_up_conversion_is_a_rotation():
    A = Y_UP_TO_Z_UP
    assert torch.allclose(A @ A.T, torch.eye(3, dtype=torch.float64))
    assert float(torch.linalg.det(A)) == pytest.approx(1.0)
    v = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    assert y_up_to_z_up(v).tolist() == [1.0, -3.0, 2.0]  # (x, y, z) -> (x, -z, y)
    assert torch.equal(A @ v, y_up_to_z_up(v))
    assert torch.equal(z_up_to_y_up(y_up_to_z_up(v)), v)


@pytest.fixture(scope="module")
def walk(cmu):
    return read_bvh(cmu / "131_01.bvh").slice(40, 100)  # frames 480-539 of the full take


class TestFK:
    def test_feature_matches_naive_fk(self, walk):
        assert (walk.global_positions() - _naive_fk(walk)).abs().max() < 1e-9

    def test_feature_global_rotations(self, walk):
        R = walk.global_rotations()
        j = walk.joint_index("LeftKnee")
        chain = [j]
        while walk.parents[chain[-1]] >= 0:
            chain.append(walk.parents[chain[-1]])
        expect = torch.eye(3, dtype=torch.float64).expand(walk.num_frames, 3, 3)
        for k in reversed(chain):
            expect = expect @ walk.rotations[:, k]
        assert (R[:, j] - expect).abs().max() < 1e-12

    def test_feature_to_skeleton_axes_follow_channels(self, walk):
        sk, theta = walk.to_skeleton()
        assert isinstance(sk, Skeleton)
        assert theta.shape == (walk.num_frames, sk.num_dofs)
        assert sk.num_dofs == 3 + sum(a.shape[0] for a in walk.axes)
        # 131 BVH arm joint "Zrotation Xrotation Yrotation": axes z, x, y of the Y-up file, Z-up
        ax = sk.joint_axes[sk.joint_index("LeftElbow")]
        assert torch.allclose(torch.tensor(ax, dtype=torch.float64),
                              torch.tensor([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 1.0]],
                                           dtype=torch.float64))
        assert sk.joint_axes[sk.joint_index("LeftToe_end")] == []
        assert torch.equal(theta[:, :3], walk.root_translation)

    def test_feature_z_up_left_at_plus_x_toes_at_minus_y(self, walk):
        p = walk.global_positions()
        rest = walk.slice(0, 1)
        rest = MotionClip(**{**rest.__dict__,
                             "rotations": torch.eye(3, dtype=torch.float64).expand(1, 38, 3, 3)})
        i = rest.joint_index
        q = rest.global_positions()[0]
        q = q - q[i("Hips")]
        assert q[i("Head_end"), 2] > 0 > q[i("LeftAnkle"), 2]  # stands along +z
        assert q[i("LeftHip"), 0] > 0 > q[i("RightHip"), 0]  # left side at +x
        assert q[i("LeftToe"), 1] < q[i("LeftAnkle"), 1]  # faces -y
        assert p[:, i("Head_end"), 2].min() > 1.2  # upright all along the walk

    def test_feature_local_translations_replace_offsets(self, walk):
        moved = torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64).repeat(walk.num_frames, 1)
        clip = MotionClip(**{**walk.__dict__, "local_translations": {"LeftKnee": moved}})
        p = clip.global_positions()
        assert (p - _naive_fk(clip)).abs().max() < 1e-9
        i = clip.joint_index
        d = (p[:, i("LeftKnee")] - p[:, i("LeftHip")]).norm(dim=-1)
        assert torch.allclose(d, torch.full_like(d, 0.1))

    def test_exception_bad_shapes(self, walk):
        with pytest.raises(ValueError, match="rotations"):
            MotionClip(**{**walk.__dict__, "rotations": walk.rotations[:, :5]})
        with pytest.raises(ValueError, match="finite"):
            bad = walk.root_translation.clone()
            bad[0, 0] = float("nan")
            MotionClip(**{**walk.__dict__, "root_translation": bad})
        with pytest.raises(ValueError, match="parent"):
            MotionClip(**{**walk.__dict__, "parents": [-1] + [5] * 37})

    def test_with_angles(self, walk):
        a = torch.full((walk.num_frames, 3), 0.2, dtype=torch.float64)
        c = walk.with_angles("LeftElbow", a)
        j = walk.joint_index("LeftElbow")
        assert torch.allclose(c.rotations[:, j], angles_to_matrix(a, walk.axes[j]))


class TestResampleSlice:
    def test_feature_slice(self, walk):
        s = walk.slice(10, 20)
        assert s.num_frames == 10
        assert torch.equal(s.rotations, walk.rotations[10:20])
        assert torch.equal(s.root_translation, walk.root_translation[10:20])
        assert walk.slice(-5).num_frames == 5
        with pytest.raises(ValueError, match="empty"):
            walk.slice(30, 10)

    def test_feature_integer_ratio_hits_source_frames(self, walk):
        r = walk.resample(30)
        assert r.fps == 30 and r.num_frames == (walk.num_frames - 1) // 4 + 1
        assert (r.rotations - walk.rotations[::4]).abs().max() < 1e-9
        assert (r.global_positions() - walk.global_positions()[::4]).abs().max() < 1e-9

    def test_feature_slerp_and_lerp_between_frames(self, walk):
        r = walk.resample(25)  # 120 -> 25: frame 1 at source time 4.8
        assert r.num_frames == math.floor((walk.num_frames - 1) * 25 / 120) + 1
        w = 0.8
        R0, R1, Rt = walk.rotations[4], walk.rotations[5], r.rotations[1]
        full, part = geodesic_angle(R0, R1), geodesic_angle(R0, Rt)
        assert torch.allclose(part, w * full, atol=1e-9)  # on the geodesic, at 80 %
        assert torch.allclose(geodesic_angle(Rt, R1), (1 - w) * full, atol=1e-9)
        lin = walk.root_translation[4] * (1 - w) + walk.root_translation[5] * w
        assert torch.allclose(r.root_translation[1], lin, atol=1e-12)

    def test_feature_one_axis_joints_stay_on_axis(self, cmu):
        from torchmocap.io import read_amc

        clip = read_amc(cmu / "01_01.amc", cmu / "01.asf").slice(0, 40).resample(25)
        sk, theta = clip.to_skeleton()
        kin_R = clip.global_rotations()
        j = clip.joint_index("ltibia")  # 1 dof (rx about C's x axis)
        p = clip.parents[j]
        local = kin_R[:, p].transpose(-1, -2) @ kin_R[:, j]
        # (1e-7: the core Skeleton keeps its axes in float32, ~1e-8 rad)
        assert (local - clip.rotations[:, j]).abs().max() < 1e-7


class TestFromSkeleton:
    def test_feature_human31_track_round_trip(self, tmp_path):
        sk = human31().to(torch.float64)
        gen = torch.Generator().manual_seed(3)
        theta = sk.zero_pose((12,), dtype=torch.float64)
        theta[:, 3:] = (torch.rand(12, sk.num_dofs - 3, generator=gen, dtype=torch.float64) - .5)
        theta[:, :3] = torch.tensor([0.1, -0.2, 0.0], dtype=torch.float64)
        clip = MotionClip.from_skeleton(sk, theta, fps=30)
        assert clip.joint_names == sk.joint_names and clip.skeleton_family == "human31"
        assert (clip.global_positions() - sk(theta).positions).abs().max() < 1e-10
        out = write_bvh(tmp_path / "track.bvh", clip)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # family and unit (metres) are recognised
            back = read_bvh(out)
        assert back.skeleton_family == "human31" and back.unit == 1.0
        cm = read_bvh(write_bvh(tmp_path / "cm.bvh", clip, unit=0.01), unit=0.01)
        assert (cm.global_positions() - back.global_positions()).abs().max() < 1e-6
        idx = [back.joint_index(n) for n in clip.joint_names]  # human31 names survive
        assert (back.global_positions()[:, idx] - sk(theta).positions).abs().max() < 1e-6
        assert back.fps == 30

    def test_exception_theta_shape(self):
        sk = human31()
        with pytest.raises(ValueError, match="theta"):
            MotionClip.from_skeleton(sk, torch.zeros(3, 5), fps=30)


def test_to_dtype_device(walk, device):
    clip = walk.slice(0, 5).to(torch.float32, device)
    assert clip.rotations.dtype == torch.float32 and clip.rotations.device.type == device.type
    p = clip.global_positions()
    assert p.dtype == torch.float32 and p.device.type == device.type
    assert (p.cpu().double() - walk.slice(0, 5).global_positions()).abs().max() < 1e-4
    r = clip.resample(60)
    assert r.num_frames == 3 and r.rotations.device.type == device.type


def test_repr_and_identity_eq(walk):
    assert repr(walk) == ("MotionClip(family='cmu_max', format='bvh', joints=38, frames=60, "
                          f"fps=120, dtype=torch.float64, source={walk.source_path!r})")
    assert walk == walk and walk != walk.slice(0)  # identity, no tensor truth-value errors
