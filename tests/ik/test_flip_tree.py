"""The interpretation tree of forwards/backwards flips of a chain (Sminchisescu & Triggs §3)."""

from __future__ import annotations

import doctest
import importlib
import math

import pytest
import torch

from torchmocap.cameras import CameraRig, look_at
from torchmocap.ik import HUMAN31_LIMBS, flip_patterns, interpretation_tree
from torchmocap.skeleton import human31, upper_body

F64 = torch.float64


def _rig(eye: torch.Tensor, target: torch.Tensor) -> CameraRig:
    R, t = look_at(eye.double(), target.double())
    K = torch.tensor([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]], dtype=F64)
    return CameraRig(K[None], R[None], t[None], (640, 480))


def _chains(n: int, K: int, gen: torch.Generator, dtype=F64) -> torch.Tensor:
    """Random chains of ``K`` links (0.2-0.45 m) around (0, 0, 1), root first."""
    root = torch.tensor([0.0, 0.0, 1.0], dtype=F64) + 0.3 * torch.randn(n, 3, generator=gen,
                                                                      dtype=F64)
    pts = [root]
    for _ in range(K):
        b = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=F64), dim=-1)
        pts.append(pts[-1] + (0.2 + 0.25 * torch.rand(n, 1, generator=gen, dtype=F64)) * b)
    return torch.stack(pts, 1).to(dtype)


def _random_poses(sk, n: int, gen: torch.Generator) -> torch.Tensor:
    lo, hi = sk.lower.double().clone(), sk.upper.double().clone()
    lo[torch.isinf(lo)], hi[torch.isinf(hi)] = -math.pi, math.pi
    th = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=gen, dtype=F64)
    if sk.root_translation:
        th[:, :3] = 0.0
        th[:, 3:6] = 0.3 * torch.randn(n, 3, generator=gen, dtype=F64)
    return th


def _random_cameras(n: int, gen: torch.Generator) -> torch.Tensor:
    """Camera centres 3-6 m from the body's vertical axis, 0.5-2.5 m high, any azimuth."""
    az = 2 * math.pi * torch.rand(n, generator=gen, dtype=F64)
    r = 3 + 3 * torch.rand(n, generator=gen, dtype=F64)
    h = 0.5 + 2 * torch.rand(n, generator=gen, dtype=F64)
    return torch.stack([r * torch.cos(az), r * torch.sin(az), h], -1)


def _limb_chains(sk, limb: str, K: int, n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    spec = HUMAN31_LIMBS[limb]
    idx = [sk.joint_index(j) for j in (spec.root,) + spec.targets[:K]]
    th = _random_poses(sk, n, g)
    return sk(th).positions[:, idx], _random_cameras(n, g)


class TestInterpretationTree:
    def test_smoke(self, device):
        chain = torch.tensor([[0.0, 0.0, 1.4], [0.0, 0.1, 1.12], [0.0, -0.1, 0.9],
                              [0.0, -0.2, 0.85]], device=device)
        tree = interpretation_tree(chain, torch.tensor([0.0, -4.0, 1.5], device=device))
        assert tree.positions.shape == (8, 4, 3) and tree.valid.shape == (8,)
        assert tree.flips.shape == (8, 3) and tree.flips.dtype == torch.bool
        assert tree.positions.device == chain.device and tree.valid.device == chain.device
        assert bool(tree.valid[0]) and torch.equal(tree.positions[0], chain)

    @pytest.mark.parametrize("K", [1, 2, 3, 4])
    def test_cardinality(self, K, dtype):
        g = torch.Generator().manual_seed(K)
        pos = _chains(6, K, g, dtype).reshape(2, 3, K + 1, 3)
        tree = interpretation_tree(pos, torch.tensor([0.0, -4.0, 1.5], dtype=dtype))
        assert tree.positions.shape == (2, 3, 2**K, K + 1, 3)
        assert tree.valid.shape == (2, 3, 2**K) and tree.num_valid.shape == (2, 3)
        assert tree.positions.dtype == dtype
        cams = torch.randn(2, 3, 3, generator=g, dtype=dtype) + torch.tensor(
            [0.0, -4.0, 1.0], dtype=dtype)
        assert interpretation_tree(pos, cams).positions.shape == (2, 3, 2**K, K + 1, 3)

    def test_feature_flip_patterns(self):
        f = flip_patterns(3)
        assert f.shape == (8, 3)
        for i in range(8):
            assert f[i].tolist() == [bool(i & 1), bool(i & 2), bool(i & 4)]

    @pytest.mark.parametrize("K", [2, 3, 4])
    def test_feature_image_consistency(self, K, dtype):
        """Every valid leaf projects every joint onto its original pixel, keeps every bone
        length and the root; leaf 0 is the input."""
        g = torch.Generator().manual_seed(10 + K)
        n = 400
        pos = _chains(n, K, g, dtype)
        rig = _rig(torch.tensor([0.7, -4.0, 1.6]), torch.tensor([0.0, 0.0, 1.0])).to(dtype)
        tree = interpretation_tree(pos, rig.camera_centers()[0])
        P, v = tree.positions, tree.valid
        assert torch.equal(P[:, 0], pos) and bool(v[:, 0].all())
        pix, depth, _ = rig.project(P.reshape(n * 2**K, K + 1, 3))
        pix = pix.reshape(n, 2**K, K + 1, 2)
        err_px = (pix - pix[:, :1]).abs().amax(dim=(-1, -2))
        L = (P[..., 1:, :] - P[..., :-1, :]).norm(dim=-1)
        err_len = (L - L[:, :1]).abs().amax(-1)
        px_tol, len_tol = (1e-7, 1e-12) if dtype == F64 else (0.05, 2e-5)
        assert float(err_px[v].max()) < px_tol
        assert float(err_len[v].max()) < len_tol
        assert bool((depth.reshape(n, 2**K, K + 1)[v] > 0).all())
        assert torch.equal(P[:, :, 0], pos[:, None, 0].expand(n, 2**K, 3))
        # power: the flipped leaves really move (decimetres)
        moved = (P - P[:, :1]).norm(dim=-1).amax(-1)[:, 1:][v[:, 1:]]
        assert float(moved.median()) > 0.1

    def test_feature_flip_bits(self):
        """Bit k flips link k: the child's side of the closest approach to its parent is the
        original side XOR the bit; leaves sharing the bits below k share joints 0..k."""
        g = torch.Generator().manual_seed(20)
        K, n = 3, 300
        pos = _chains(n, K, g)
        c = torch.tensor([0.3, -4.0, 1.5], dtype=F64)
        tree = interpretation_tree(pos, c)
        P, v, f = tree.positions, tree.valid, tree.flips
        d = torch.nn.functional.normalize(pos[:, 1:] - c, dim=-1)  # (n, K, 3) original rays
        side = ((P[:, :, 1:] - P[:, :, :-1]) * d[:, None]).sum(-1) >= 0  # (n, 2^K, K)
        # ignore near-tangent links where the two roots (and sides) coincide
        s = ((P[:, :, 1:] - P[:, :, :-1]) * d[:, None]).sum(-1).abs()
        clear = s > 1e-6
        expect = side[:, :1] ^ f[None]
        ok = (side == expect) | ~clear
        assert bool(ok[v].all())
        for i in range(2**K):
            for k in range(K):
                low = i & ((1 << k) - 1)  # same bits below k
                assert torch.equal(P[:, i, : k + 1], P[:, low, : k + 1])

    def test_feature_pruning_matches_brute_force(self):
        """A leaf is invalid exactly when some ray misses the sphere around its (moved) parent
        or the root lies behind the camera — checked independently with the cross-product
        distance from the parent to the ray."""
        g = torch.Generator().manual_seed(21)
        K, n = 3, 1000
        pos = _chains(n, K, g)
        c = torch.tensor([0.0, -3.0, 1.2], dtype=F64)
        tree = interpretation_tree(pos, c)
        P, v = tree.positions, tree.valid
        assert 0 < int((~v).sum()) < v.numel() // 2  # pruning happens, but not mostly
        d = torch.nn.functional.normalize(pos[:, 1:] - c, dim=-1)  # (n, K, 3)
        L = (pos[:, 1:] - pos[:, :-1]).norm(dim=-1)
        ok = torch.ones(n, 2**K, dtype=torch.bool)
        for k in range(K):
            parent = P[:, :, k]  # (n, 2^K, 3)
            dist = torch.linalg.cross(parent - c, d[:, None, k].expand_as(parent)).norm(dim=-1)
            reach = dist <= L[:, None, k] * (1 + 1e-9)
            front = ((P[:, :, k + 1] - c) * d[:, None, k]).sum(-1) > 0
            ok &= reach & front
        # tangent cases (|dist - L| ~ rounding) may go either way
        assert int((ok != v).sum()) <= 2

    @pytest.mark.parametrize(
        ("skeleton", "limb", "K", "lo", "hi"),
        [("human31", "l_leg", 3, 6.2, 7.1), ("human31", "r_arm", 2, 3.4, 3.95),
         ("upper_body", "l_arm", 3, 6.3, 7.2)],
    )
    def test_feature_valid_fraction(self, skeleton, limb, K, lo, hi):
        """Most leaves survive for real limbs seen from real camera positions: REFERENCE §7
        quotes ~6.6 of 8 for a 3-link limb (measured here: human31 leg 6.64, upper_body arm
        6.74-6.79, human31 arm 3.70 of 4 over 2000 random in-limit poses)."""
        sk = (human31() if skeleton == "human31" else upper_body()).double()
        pos, cams = _limb_chains(sk, limb, K, 2000, seed=30)
        tree = interpretation_tree(pos, cams)
        mean = float(tree.num_valid.double().mean())
        assert lo < mean < hi
        assert int(tree.num_valid.min()) >= 2  # the root link's two roots always exist

    def test_exception(self):
        c = torch.zeros(3)
        with pytest.raises(ValueError, match="positions"):
            interpretation_tree(torch.zeros(1, 3), c)
        with pytest.raises(ValueError, match="positions"):
            interpretation_tree(torch.zeros(4, 2), c)
        with pytest.raises(ValueError, match="at most 16"):
            interpretation_tree(torch.rand(18, 3) + 2, c)
        with pytest.raises(ValueError, match="camera_center"):
            interpretation_tree(torch.rand(3, 3) + 2, torch.zeros(2))
        with pytest.raises(ValueError, match="positions"):
            interpretation_tree(torch.full((3, 3), math.nan), c)
        with pytest.raises(ValueError, match="camera_center"):
            interpretation_tree(torch.zeros(3, 3), c)  # a joint at the camera centre
        with pytest.raises(TypeError, match="positions"):
            interpretation_tree([[0.0, 0.0, 1.0]], c)
        with pytest.raises(ValueError, match="num_links"):
            flip_patterns(0)

    def test_feature_float32_matches_float64(self):
        g = torch.Generator().manual_seed(40)
        pos = _chains(500, 3, g)
        c = torch.tensor([0.3, -4.0, 1.5], dtype=F64)
        t64 = interpretation_tree(pos, c)
        t32 = interpretation_tree(pos.float(), c.float())
        same = t64.valid == t32.valid
        assert float(same.double().mean()) > 0.995
        both = t64.valid & t32.valid
        assert float((t32.positions.double() - t64.positions).norm(dim=-1).amax(-1)[both].max()
                     ) < 1e-3

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(41)
        pos = _chains(2, 2, g)[:1].requires_grad_()
        c = torch.tensor([0.3, -4.0, 1.5], dtype=F64)
        tree = interpretation_tree(pos.detach(), c)
        assert bool(tree.valid.all())  # a chain without pruned (non-smooth) leaves
        assert torch.autograd.gradcheck(lambda p: interpretation_tree(p, c).positions, (pos,))


def test_docstring_examples():
    module = importlib.import_module("torchmocap.ik.flip_tree")
    res = doctest.testmod(module, extraglobs={"torch": torch})
    assert res.attempted > 0 and res.failed == 0
