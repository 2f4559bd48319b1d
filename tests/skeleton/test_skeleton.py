"""Skeleton FK: against an independent loop implementation and pytorch-kinematics, invariants,
gradients, errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.geometry import axis_angle_rotation
from torchmocap.skeleton import (
    Skeleton,
    SkeletonError,
    human31,
    pk_theta,
    preset,
    to_pytorch_kinematics_chain,
    upper_body,
    write_urdf,
)


def _random_theta(sk, n, gen, dtype=torch.float32):
    lo = sk.lower.double().clamp(min=-math.pi)
    hi = sk.upper.double().clamp(max=math.pi)
    th = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=gen, dtype=torch.float64)
    if sk.root_translation:
        th[:, :3] = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    return th.to(dtype)


def _loop_fk(sk, th):
    """Independent, per-joint loop implementation (the definition, written plainly)."""
    J = sk.num_joints
    R, p = [None] * J, [None] * J
    trans = set(sk.translation_dofs)
    for j, name in enumerate(sk.joint_names):
        dofs = [d for d in sk.joint_dofs(name) if d not in trans]
        L = torch.eye(3, dtype=th.dtype).expand(*th.shape[:-1], 3, 3)
        for a, d in zip(sk.joint_axes[j], dofs):
            ax = torch.tensor(a, dtype=th.dtype).expand(*th.shape[:-1], 3)
            L = L @ axis_angle_rotation(ax, th[..., d])
        off = sk.offsets[j].to(th.dtype)
        if sk.parents[j] < 0:
            R[j] = L
            p[j] = off + (th[..., :3] if sk.root_translation else torch.zeros_like(th[..., :3]))
        else:
            q = sk.parents[j]
            R[j] = R[q] @ L
            p[j] = p[q] + (R[q] @ off[:, None])[..., 0]
    return torch.stack(R, -3), torch.stack(p, -2)


TOY = {
    "name": "toy",
    "joints": [
        {"name": "root", "parent": None, "offset": [0, 0, 1], "axes": [[0, 0, 1]]},
        {"name": "a", "parent": "root", "offset": [0.5, 0, 0], "axes": [[0, 1, 0], [1, 0, 0]]},
        {"name": "fixed", "parent": "a", "offset": [0.2, 0, 0]},
        {"name": "b", "parent": "fixed", "offset": [0.3, 0, 0], "axes": [[0, 0, 1]],
         "limits": [[-1.0, 1.0]]},
        {"name": "tip", "parent": "b", "offset": [0.25, 0, 0]},
    ],
}


OBLIQUE = {  # axes that float32 cannot represent exactly (like the C frames of ASF skeletons)
    "name": "oblique",
    "joints": [
        {"name": "root", "parent": None, "offset": [0.1, 0.2, 0.9], "axes": [[0.6, 0.8, 0.0]]},
        {"name": "a", "parent": "root", "offset": [0.31, 0.07, 0.0],
         "axes": [[0.0, 0.28, 0.96], [1 / 3**0.5, 1 / 3**0.5, 1 / 3**0.5]]},
        {"name": "b", "parent": "a", "offset": [0.27, 0.0, 0.11], "axes": [[0.36, 0.0, 0.48]]},
        {"name": "tip", "parent": "b", "offset": [0.25, 0.0, 0.0]},
    ],
}


class TestSkeleton:
    def test_smoke(self, device, dtype):
        sk = human31().to(device=device, dtype=dtype)
        k = sk(sk.zero_pose((4,)))
        assert k.positions.shape == (4, sk.num_joints, 3)
        assert k.rotations.shape == (4, sk.num_joints, 3, 3)
        assert k.transforms.shape == (4, sk.num_joints, 4, 4)
        assert k.positions.dtype == dtype and k.positions.device == device

    def test_human31_layout(self):
        sk = human31()
        assert sk.num_dofs == 31
        counts = {n: len(sk.joint_dofs(n)) for n in sk.joint_names}
        assert counts["pelvis"] == 6 and counts["spine"] == 3 and counts["neck"] == 2
        for side in "lr":
            assert counts[f"{side}_shoulder"] == 3 and counts[f"{side}_elbow"] == 1
            assert counts[f"{side}_hip"] == 3 and counts[f"{side}_knee"] == 1
            assert counts[f"{side}_ankle"] == 2
        # stature ~1.75 m, feet near the floor
        p = sk(sk.zero_pose()).positions
        assert abs(p[sk.joint_index("head_top"), 2].item() - 1.75) < 0.03
        assert p[:, 2].min().item() >= 0.0
        # each 3-DoF joint: mutually perpendicular axes (analytic IK always solvable)
        for j, axes in enumerate(sk.joint_axes):
            if len(axes) == 3:
                A = torch.tensor(axes)
                assert torch.allclose(A @ A.T, torch.eye(3), atol=1e-6), sk.joint_names[j]
        # limits are finite for every non-root DoF and contain zero
        rot = [d for d in range(sk.num_dofs) if not sk.dof_names[d].startswith("pelvis")]
        assert torch.isfinite(sk.lower[rot]).all() and torch.isfinite(sk.upper[rot]).all()
        assert (sk.lower[rot] <= 0).all() and (sk.upper[rot] >= 0).all()

    def test_anatomical_signs(self):
        """Positive knee/elbow/hip flexion bends the way a human joint does (facing -y)."""
        sk = human31()
        th = sk.zero_pose()
        th[sk.dof_index("l_knee_flex")] = 1.0
        th[sk.dof_index("l_elbow_flex")] = 1.0
        th[sk.dof_index("r_hip_flex")] = 1.0
        p = sk(th).positions
        j = sk.joint_index
        assert p[j("l_ankle"), 1] > 0.2  # shank swings backwards (+y)
        assert p[j("l_wrist"), 1] < -0.1  # forearm comes forwards (-y)
        assert p[j("r_knee"), 1] < -0.2  # thigh swings forwards
        th = sk.zero_pose()
        th[sk.dof_index("l_shoulder_abd")] = 1.0
        th[sk.dof_index("r_shoulder_abd")] = 1.0
        p = sk(th).positions
        assert p[j("l_elbow"), 0] > 0.3 and p[j("r_elbow"), 0] < -0.3  # both arms go outwards

    @pytest.mark.parametrize("make", [human31, upper_body, lambda: Skeleton.from_dict(TOY),
                                      lambda: Skeleton.from_dict(OBLIQUE)])
    def test_feature_vs_loop(self, make):
        sk = make().double()
        gen = torch.Generator().manual_seed(0)
        th = _random_theta(sk, 64, gen, torch.float64).reshape(4, 16, -1)
        k = sk(th)
        R, p = _loop_fk(sk, th)
        assert torch.allclose(k.rotations, R, atol=1e-12)
        assert torch.allclose(k.positions, p, atol=1e-12)

    @pytest.mark.parametrize("name", ["human31", "upper_body"])
    def test_vs_pytorch_kinematics(self, name, tmp_path):
        sk = preset(name)
        chain = to_pytorch_kinematics_chain(sk)
        gen = torch.Generator().manual_seed(1)
        th = _random_theta(sk, 256, gen)
        th = sk.clamp(th)
        assert sk.within_limits(th).all()
        fr = chain.forward_kinematics(pk_theta(chain, sk, th))
        k = sk(th)
        for i, n in enumerate(sk.joint_names):
            M = fr[n].get_matrix()
            assert (M[:, :3, 3] - k.positions[:, i]).abs().max() < 1e-5, n
            assert (M[:, :3, :3] - k.rotations[:, i]).abs().max() < 1e-5, n
        path = write_urdf(sk, tmp_path / f"{name}.urdf")
        assert path.read_text().startswith("<robot")

    def test_invariants(self):
        sk = human31().double()
        gen = torch.Generator().manual_seed(2)
        th = torch.randn(100, sk.num_dofs, generator=gen, dtype=torch.float64) * 2
        k = sk(th)
        rest = sk(sk.zero_pose()).positions
        # bone lengths preserved for any theta
        for j in range(1, sk.num_joints):
            q = sk.parents[j]
            L = (k.positions[:, j] - k.positions[:, q]).norm(dim=-1)
            assert torch.allclose(L, (rest[j] - rest[q]).norm().expand(100), atol=1e-12)
        # rotations are proper
        RtR = k.rotations.transpose(-1, -2) @ k.rotations
        assert torch.allclose(RtR, torch.eye(3, dtype=torch.float64).expand_as(RtR), atol=1e-12)
        # zero pose = rest pose: positions are the cumulative offsets, rotations identity
        k0 = sk(sk.zero_pose())
        cum = torch.zeros(sk.num_joints, 3, dtype=torch.float64)
        for j in range(sk.num_joints):
            q = sk.parents[j]
            cum[j] = sk.offsets[j] + (cum[q] if q >= 0 else 0)
        assert torch.allclose(k0.positions, cum)
        assert torch.allclose(k0.rotations, torch.eye(3, dtype=torch.float64).expand_as(
            k0.rotations))
        # root translation moves everything rigidly
        t = sk.zero_pose()
        t[:3] = torch.tensor([0.3, -1.0, 0.2], dtype=torch.float64)
        assert torch.allclose(sk(t).positions - cum, t[:3].expand_as(cum))

    def test_gradcheck_theta_and_offsets(self):
        sk = Skeleton.from_dict(TOY).double()
        th = torch.randn(3, sk.num_dofs, dtype=torch.float64, requires_grad=True)
        off = sk.offsets.clone().requires_grad_(True)

        def f(t, o):
            k = sk(t, offsets=o)
            return k.positions, k.rotations

        assert torch.autograd.gradcheck(f, (th, off))
        sk31 = human31().double()
        th = torch.randn(2, 31, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda t: sk31(t).positions, (th,))

    def test_offsets_per_particle_and_buffer_grad(self):
        sk = human31()
        th = torch.randn(5, 31)
        off = sk.offsets.expand(5, -1, -1).clone()
        off[2] *= 1.1
        p = sk(th, offsets=off).positions
        assert torch.allclose(p[[0, 1, 3, 4]], sk(th[[0, 1, 3, 4]]).positions, atol=1e-6)
        assert not torch.allclose(p[2], sk(th[2]).positions)
        # autograd w.r.t. the module's own offsets (bone lengths as parameters)
        sk.offsets.requires_grad_(True)
        sk(th).positions[:, sk.joint_index("l_hand")].sum().backward()
        assert sk.offsets.grad is not None
        assert sk.offsets.grad[sk.joint_index("l_elbow")].abs().sum() > 0
        assert sk.offsets.grad[sk.joint_index("r_knee")].abs().sum() == 0

    def test_with_bone_lengths(self):
        sk = human31()
        sk2 = sk.with_bone_lengths({"l_knee": 0.5, "l_ankle": 0.38})
        assert abs(sk2.bone_lengths()["l_knee"] - 0.5) < 1e-6
        assert abs(sk2.bone_lengths()["l_ankle"] - 0.38) < 1e-6
        assert abs(sk2.bone_lengths()["r_knee"] - sk.bone_lengths()["r_knee"]) < 1e-7
        big = sk.with_bone_lengths(scale=1.1)
        h = big(big.zero_pose()).positions[big.joint_index("head_top"), 2]
        assert abs(h.item() - 1.1 * 1.75) < 1e-4
        with pytest.raises(KeyError, match="unknown joint 'knee'"):
            sk.with_bone_lengths({"knee": 0.4})
        with pytest.raises(ValueError, match="finite length"):
            sk.with_bone_lengths({"l_knee": float("nan")})

    def test_limits(self):
        sk = human31()
        th = torch.full((2, 31), 10.0)
        c = sk.clamp(th)
        assert sk.within_limits(c).all()
        assert not sk.within_limits(th).any()
        assert c[0, sk.dof_index("l_knee_flex")].item() == pytest.approx(math.radians(135))

    def test_round_trip_dict(self):
        sk = human31()
        sk2 = Skeleton.from_dict(sk.to_dict())
        th = torch.randn(10, 31)
        assert torch.allclose(sk(th).positions, sk2(th).positions)
        assert sk2.dof_names == sk.dof_names

    def test_lookups(self):
        sk = human31()
        assert sk.joint_names[sk.joint_index("l_knee")] == "l_knee"
        assert sk.dof_names[sk.dof_index("l_knee_flex")] == "l_knee_flex"
        assert sk.child_joints("spine") == ["neck", "l_shoulder", "r_shoulder"]
        with pytest.raises(KeyError, match="unknown joint 'kneee'"):
            sk.joint_index("kneee")
        with pytest.raises(KeyError, match="unknown DoF"):
            sk.dof_index("knee")
        k = sk(sk.zero_pose())
        R, p = k.joint("l_knee")
        assert p.shape == (3,) and R.shape == (3, 3)

    def test_exception(self):
        sk = human31()
        with pytest.raises(ValueError, match=r"theta: expected shape \(\.\.\., 31\)"):
            sk(torch.zeros(3, 30))
        with pytest.raises(ValueError, match="theta: expected finite"):
            sk(torch.full((31,), float("nan")))
        with pytest.raises(TypeError, match="theta"):
            sk([0.0] * 31)

    @pytest.mark.parametrize(
        "mutate, match",
        [
            (lambda s: s["joints"][1].update(parent="nowhere"), "parent 'nowhere'"),
            (lambda s: s["joints"][1].update(axes=[[0, 0, 0]]), "zero-length"),
            (lambda s: s["joints"][0].update(parent="tip"), "exactly one root"),
            (lambda s: (s["joints"][0].update(parent="tip"),
                        s["joints"].append({"name": "r2", "parent": None})), "not connected"),
            (lambda s: s["joints"].append(dict(s["joints"][1])), "duplicate"),
            (lambda s: s["joints"][3].update(limits=[[1.0, -1.0]]), "lower"),
            (lambda s: s["joints"][1].update(axes=[[1, 0, 0]] * 4), "at most 3"),
            (lambda s: s["joints"][1].update(offset=[0, 1]), "offset"),
            (lambda s: s.update(joints=[]), "non-empty"),
        ],
    )
    def test_malformed_dicts(self, mutate, match):
        import copy

        spec = copy.deepcopy(TOY)
        mutate(spec)
        with pytest.raises(SkeletonError, match=match):
            Skeleton.from_dict(spec)

    def test_yaml(self, tmp_path):
        import yaml

        p = tmp_path / "toy.yaml"
        p.write_text(yaml.safe_dump(TOY))
        sk = Skeleton.from_yaml(p)
        assert sk.joint_names == ["root", "a", "fixed", "b", "tip"]
        assert sk.num_dofs == 3 + 1 + 2 + 1
        with pytest.raises(KeyError, match="unknown skeleton preset"):
            preset("robot")


def test_jacobian_matches_autograd_and_finite_differences():
    from torchmocap.geometry import so3_log

    sk = human31().double()
    th = torch.randn(3, 31, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    kin, Jp, Jr = sk.jacobian(th)
    Ja = torch.autograd.functional.jacobian(lambda t: sk(t).positions, th)
    Ja = torch.stack([Ja[b, :, :, b] for b in range(3)])
    assert (Ja - Jp).abs().max() < 1e-12
    eps = 1e-6
    for d in range(31):
        t2 = th.clone()
        t2[:, d] += eps
        w = so3_log(sk(t2).rotations @ kin.rotations.transpose(-1, -2)) / eps
        assert (w - Jr[..., d]).abs().max() < 1e-5, sk.dof_names[d]


@pytest.mark.parametrize("spec", ["toy", "oblique", "no_translation"])
@pytest.mark.parametrize("batch", [(), (2, 3)])
def test_jacobian_of_other_skeletons_and_batch_shapes(spec, batch):
    """The vectorised Jacobian on skeletons with fixed joints, two-axis joints, oblique axes and
    no root translation, for an unbatched pose and a 2-D batch: autograd of the forward
    kinematics (positions) and finite differences of the rotations."""
    from torchmocap.geometry import so3_log

    d = {"toy": TOY, "oblique": OBLIQUE}.get(spec)
    if d is None:
        d = {"name": "nt", "joints": [dict(j) for j in TOY["joints"]]}
        d["joints"][0]["translation"] = False
    sk = Skeleton.from_dict(d).double()
    g = torch.Generator().manual_seed(11)
    th = torch.randn(*batch, sk.num_dofs, dtype=torch.float64, generator=g)
    kin, Jp, Jr = sk.jacobian(th)
    assert Jp.shape == Jr.shape == (*batch, sk.num_joints, 3, sk.num_dofs)
    flat = th.reshape(-1, sk.num_dofs)
    Ja = torch.autograd.functional.jacobian(lambda t: sk(t).positions, flat)
    Ja = torch.stack([Ja[b, :, :, b] for b in range(flat.shape[0])])
    torch.testing.assert_close(Jp.reshape(Ja.shape), Ja, atol=1e-12, rtol=0)
    eps = 1e-6
    for k in range(sk.num_dofs):
        t2 = th.clone()
        t2[..., k] += eps
        w = so3_log(sk(t2).rotations @ kin.rotations.transpose(-1, -2)) / eps
        assert (w - Jr[..., k]).abs().max() < 1e-5, sk.dof_names[k]
    # float32 gives the float64 result to float32 precision
    _, Jp32, Jr32 = sk.float().jacobian(th.float())
    torch.testing.assert_close(Jp32.double(), Jp, atol=2e-5, rtol=0)
    torch.testing.assert_close(Jr32.double(), Jr, atol=2e-5, rtol=0)


def test_jacobian_is_differentiable():
    """Second-order use (a gradient through the Jacobian): gradcheck on the toy skeleton."""
    sk = Skeleton.from_dict(TOY).double()
    th = torch.randn(2, sk.num_dofs, dtype=torch.float64,
                     generator=torch.Generator().manual_seed(2)).requires_grad_(True)

    def f(t):
        _, Jp, Jr = sk.jacobian(t)
        return Jp, Jr

    assert torch.autograd.gradcheck(f, (th,), eps=1e-6, atol=1e-6)
