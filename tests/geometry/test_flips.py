"""Kinematic flips under perspective: ray–sphere roots, the stable discriminant, flip_child."""

from __future__ import annotations

import doctest
import math

import pytest
import torch

import torchmocap.geometry.flips as flips_module
from torchmocap.cameras import CameraRig, look_at
from torchmocap.geometry import RaySphereIntersection, flip_child, ray_sphere_intersections

F64 = torch.float64


def _rig(eye: torch.Tensor, target: torch.Tensor) -> CameraRig:
    """One pinhole camera (640 x 480, f = 800 px) at ``eye`` looking at ``target``."""
    R, t = look_at(eye.double(), target.double())
    K = torch.tensor([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]], dtype=F64)
    return CameraRig(K[None], R[None], t[None], (640, 480))


def _links(n: int, gen: torch.Generator, dtype=F64, dist=(3.0, 6.0)):
    """Camera at a random point, parent 3-6 m in front of it, child 0.2-0.5 m from the parent."""
    c = torch.randn(n, 3, generator=gen, dtype=F64)
    u = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=F64), dim=-1)
    r = dist[0] + (dist[1] - dist[0]) * torch.rand(n, generator=gen, dtype=F64)
    P = c + r[:, None] * u
    b = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=F64), dim=-1)
    L = 0.2 + 0.3 * torch.rand(n, generator=gen, dtype=F64)
    X = P + L[:, None] * b
    return c.to(dtype), P.to(dtype), X.to(dtype)


def _near_tangent(n: int, rel: float, gen: torch.Generator, L: float = 0.3):
    """float32 inputs ``(c, P, X, L)`` whose float64 construction has ``Delta = +-rel L^2``: the
    ray from the camera ``c`` through the child ``X`` passes at ``L sqrt(1 -+ rel)`` from the
    parent ``P`` (3-6 m from the camera, a realistic mocap geometry). Returns the float32
    inputs, the construction's sign and the exact sign for the float32 inputs (float64
    arithmetic on the rounded values, where ``Delta`` is exact to ~1e-16 L^2)."""
    c = 2 * torch.randn(n, 3, generator=gen, dtype=F64)
    u = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=F64), dim=-1)
    r = 3 + 3 * torch.rand(n, generator=gen, dtype=F64)
    P = c + r[:, None] * u
    sign = torch.where(torch.rand(n, generator=gen, dtype=F64) < 0.5, -1.0, 1.0).to(F64)
    perp = L * torch.sqrt(1 - rel * sign)
    w = torch.nn.functional.normalize(
        torch.linalg.cross(u, torch.randn(n, 3, generator=gen, dtype=F64)), dim=-1)
    s = perp / r
    d = torch.sqrt(1 - s * s)[:, None] * u + s[:, None] * w
    t = (d * (P - c)).sum(-1)
    X = c + (t + 0.3 * L * torch.randn(n, generator=gen, dtype=F64))[:, None] * d
    c32, P32, X32 = c.float(), P.float(), X.float()
    L32 = torch.tensor(L, dtype=torch.float32)
    cc, PP, XX, LL = c32.double(), P32.double(), X32.double(), L32.double()
    dd = torch.nn.functional.normalize(XX - cc, dim=-1)
    cr = torch.linalg.cross(dd, PP - cc)  # |d x m| = distance from P to the ray
    exact = LL * LL - (cr * cr).sum(-1) > 0
    return (c32, P32, X32, L32), sign > 0, exact


def _naive_hit(c, P, X, L):
    d = torch.nn.functional.normalize(X - c, dim=-1)
    m = P - c
    tc = (d * m).sum(-1)
    return tc * tc - (m * m).sum(-1) + L * L > 0


class TestRaySphereIntersections:
    def test_smoke(self, device):
        r = ray_sphere_intersections(torch.zeros(3, device=device),
                                     torch.tensor([0.0, 0.0, 1.0], device=device),
                                     torch.tensor([0.0, 0.1, 3.0], device=device), 0.3)
        assert isinstance(r, RaySphereIntersection)
        root = math.sqrt(0.09 - 0.01)
        assert r.lam_minus.item() == pytest.approx(3 - root, abs=1e-6)
        assert r.lam_plus.item() == pytest.approx(3 + root, abs=1e-6)
        assert bool(r.hit) and r.hit.device == r.lam_minus.device

    def test_cardinality(self, device, dtype):
        g = torch.Generator().manual_seed(0)
        o = torch.randn(5, 1, 3, generator=g, dtype=dtype).to(device)
        d = torch.randn(4, 3, generator=g, dtype=dtype).to(device)
        s = torch.randn(4, 3, generator=g, dtype=dtype).to(device)
        r = ray_sphere_intersections(o, d, s, torch.full((5, 4), 0.5, dtype=dtype, device=device))
        assert r.lam_minus.shape == r.lam_plus.shape == r.hit.shape == (5, 4)
        assert r.lam_minus.dtype == dtype and r.hit.dtype == torch.bool

    def test_feature_roots_on_ray_and_sphere(self, device):
        g = torch.Generator().manual_seed(1)
        n = 5000
        o = torch.randn(n, 3, generator=g, dtype=F64)
        d = torch.randn(n, 3, generator=g, dtype=F64) * 3  # not unit: normalised inside
        s = torch.randn(n, 3, generator=g, dtype=F64)
        rad = torch.rand(n, generator=g, dtype=F64) * 2
        r = ray_sphere_intersections(o.to(device), d.to(device), s.to(device), rad.to(device))
        lm, lp, hit = r.lam_minus.cpu(), r.lam_plus.cpu(), r.hit.cpu()
        assert 0.1 < float(hit.double().mean()) < 0.9  # both cases occur
        du = d / d.norm(dim=-1, keepdim=True)
        for lam in (lm, lp):
            dist = (o + lam[:, None] * du - s).norm(dim=-1)
            assert float((dist - rad)[hit].abs().max()) < 1e-12
        assert bool((lm <= lp).all())
        # on a miss both are the closest approach: the perpendicular foot, farther than r
        foot = o + lm[:, None] * du
        assert float(((foot - s) * du).sum(-1)[~hit].abs().max()) < 1e-12
        assert bool(((foot - s).norm(dim=-1)[~hit] > rad[~hit]).all())
        assert bool((lm[~hit] == lp[~hit]).all())

    def test_feature_origin_anywhere_on_the_line(self):
        g = torch.Generator().manual_seed(2)
        o = torch.randn(100, 3, generator=g, dtype=F64)
        d = torch.nn.functional.normalize(torch.randn(100, 3, generator=g, dtype=F64), dim=-1)
        s = o + 2 * d + 0.1 * torch.randn(100, 3, generator=g, dtype=F64)
        a = ray_sphere_intersections(o, d, s, 0.5)
        b = ray_sphere_intersections(o + 1.5 * d, d, s, 0.5)
        torch.testing.assert_close(b.lam_minus + 1.5, a.lam_minus, rtol=0, atol=1e-12)
        torch.testing.assert_close(b.lam_plus + 1.5, a.lam_plus, rtol=0, atol=1e-12)

    def test_exception(self):
        z = torch.zeros(3)
        with pytest.raises(ValueError, match="direction"):
            ray_sphere_intersections(z, z, z, 1.0)
        with pytest.raises(ValueError, match="origin"):
            ray_sphere_intersections(torch.zeros(4), torch.ones(3), z, 1.0)
        with pytest.raises(ValueError, match="radius"):
            ray_sphere_intersections(z, torch.ones(3), z, -1.0)
        with pytest.raises(ValueError, match="sphere_center"):
            ray_sphere_intersections(z, torch.ones(3), torch.full((3,), math.nan), 1.0)
        with pytest.raises(TypeError, match="origin"):
            ray_sphere_intersections([0.0, 0.0, 0.0], torch.ones(3), z, 1.0)

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(3)
        o = torch.randn(6, 3, generator=g, dtype=F64)
        d = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=F64), dim=-1)
        s = (o + 2 * d + 0.1 * torch.randn(6, 3, generator=g, dtype=F64)).requires_grad_()
        o.requires_grad_()
        d.requires_grad_()
        rad = torch.full((6,), 0.5, dtype=F64, requires_grad=True)

        def f(o, d, s, rad):
            r = ray_sphere_intersections(o, d, s, rad)
            return r.lam_minus, r.lam_plus

        assert torch.autograd.gradcheck(f, (o, d, s, rad))


class TestFlipChild:
    def test_smoke(self, device):
        c = torch.zeros(3, device=device)
        P = torch.tensor([0.0, 0.0, 3.0], device=device)
        X = torch.tensor([0.3, 0.0, 3.0], device=device)
        flipped, valid = flip_child(P, X, c)
        # the ray through X passes at 3 sin(atan(0.1)) from P: the flip is nearer the camera
        assert bool(valid) and flipped.device == X.device
        assert flipped.norm() < X.norm()
        assert (flipped - P).norm().item() == pytest.approx(0.3, abs=1e-6)

    def test_cardinality(self, dtype):
        g = torch.Generator().manual_seed(0)
        c, P, X = _links(12, g, dtype)
        f, v = flip_child(P.reshape(3, 4, 3), X.reshape(3, 4, 3), c[0])
        assert f.shape == (3, 4, 3) and v.shape == (3, 4) and f.dtype == dtype
        f, v = flip_child(P[:4], X[:4], c[:4], length=torch.full((4,), 0.3, dtype=dtype))
        assert f.shape == (4, 3) and v.shape == (4,)

    @pytest.mark.parametrize("use_length", [False, True])
    def test_feature_same_pixel_same_length(self, use_length):
        g = torch.Generator().manual_seed(4)
        n = 2000
        target = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
        eye = torch.tensor([0.5, -4.0, 1.6], dtype=F64)
        rig = _rig(eye, target)
        c = rig.camera_centers()[0]
        P = target + 0.4 * torch.randn(n, 3, generator=g, dtype=F64)
        b = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=-1)
        L = 0.2 + 0.3 * torch.rand(n, generator=g, dtype=F64)
        X = P + L[:, None] * b
        flipped, valid = flip_child(P, X, c, length=L if use_length else None)
        assert bool(valid.all())  # every child of these in-front links has an in-front flip
        pix, depth, _ = rig.project(torch.stack([X, flipped], 1))
        assert float((pix[:, 0, 0] - pix[:, 0, 1]).abs().max()) < 1e-8  # pixels
        assert bool((depth > 0).all())
        assert float(((flipped - P).norm(dim=-1) - L).abs().max()) < 1e-12
        # a real move (the test has power): typical flips move the child by decimetres
        moved = (flipped - X).norm(dim=-1)
        assert float(moved.median()) > 0.1

    def test_feature_flip_twice_is_identity(self, dtype):
        g = torch.Generator().manual_seed(5)
        c, P, X = _links(3000, g, dtype)
        f1, v1 = flip_child(P, X, c)
        f2, v2 = flip_child(P, f1, c)
        tol = 1e-12 if dtype == F64 else 2e-5
        assert bool(v1.all() & v2.all())
        assert float((f2 - X).abs().max()) < tol
        L = (X - P).norm(dim=-1)
        h1, w1 = flip_child(P, X, c, length=L)
        h2, _ = flip_child(P, h1, c, length=L)
        assert bool(w1.all())
        assert float((h2 - X).abs().max()) < (1e-12 if dtype == F64 else 1e-4)

    def test_feature_other_length(self):
        """With a new length the child is re-attached on its ray at that distance, on the
        other side of the closest approach; flipping that gives the root on the original
        side."""
        g = torch.Generator().manual_seed(6)
        c, P, X = _links(2000, g)
        L2 = (X - P).norm(dim=-1) * 1.1
        f, v = flip_child(P, X, c, length=L2)
        assert float(v.double().mean()) > 0.9
        d = torch.nn.functional.normalize(X - c, dim=-1)
        assert float(torch.linalg.cross(f - c, d).norm(dim=-1)[v].max()) < 1e-12  # on the ray
        assert float(((f - P).norm(dim=-1) - L2)[v].abs().max()) < 1e-12
        tc = (d * (P - c)).sum(-1)
        side = lambda x: ((x - c) * d).sum(-1) > tc  # noqa: E731
        assert bool((side(f) != side(X))[v].all())
        back, _ = flip_child(P, f, c, length=L2)
        assert bool((side(back) == side(X))[v].all())

    def test_feature_miss_and_behind_camera_are_invalid(self, device):
        c = torch.zeros(3, dtype=F64, device=device)
        P = torch.tensor([0.0, 0.0, 3.0], dtype=F64, device=device)
        X = torch.tensor([0.3, 0.0, 3.0], dtype=F64, device=device)
        # the ray passes 0.2985 m from P: a 0.2 m bone cannot reach it
        f, v = flip_child(P, X, c, length=0.2)
        assert not bool(v) and bool(torch.isfinite(f).all())
        # the camera inside the parent's sphere: the other root is behind the camera
        P2 = torch.tensor([0.0, 0.0, 0.1], dtype=F64, device=device)
        X2 = torch.tensor([0.0, 0.0, 0.4], dtype=F64, device=device)
        f2, v2 = flip_child(P2, X2, c)
        assert not bool(v2)
        torch.testing.assert_close(f2, torch.tensor([0.0, 0.0, -0.2], dtype=F64, device=device))

    def test_feature_float32_matches_float64(self):
        g = torch.Generator().manual_seed(7)
        c, P, X = _links(3000, g)
        f64, _ = flip_child(P, X, c)
        f32, _ = flip_child(P.float(), X.float(), c.float())
        assert float((f32.double() - f64).abs().max()) < 2e-5

    def test_feature_near_tangent_sign_float32(self):
        """The stable discriminant keeps the sign where the naive one fails (REFERENCE §7).

        ``|Delta| = 1e-5 L^2``, camera 3-6 m away: the naive ``t^2 - |m|^2 + L^2`` gets the
        sign wrong in about a third of the cases, the stable form in none."""
        g = torch.Generator().manual_seed(8)
        (c, P, X, L), built, exact = _near_tangent(20000, 1e-5, g)
        assert bool((built == exact).all())  # rounding to float32 keeps the sign at 1e-5
        naive_wrong = (_naive_hit(c, P, X, L) != exact).double().mean()
        assert float(naive_wrong) > 0.2  # the test data has power
        d = X - c
        for origin in (c, X):  # camera-anchored and child-anchored
            hit = ray_sphere_intersections(origin, d, P, L).hit
            assert int((hit != exact).sum()) == 0
        # flip_child with a length prunes with the same stable test
        _, valid = flip_child(P, X, c, length=L)
        assert int((valid != exact).sum()) == 0

    def test_feature_near_tangent_child_anchor_float32(self):
        """At ``|Delta| = 1e-6 L^2`` the naive form is a coin toss; the stable form anchored at
        the child (as :func:`flip_child` and the interpretation tree use it) errs far less
        than anchored at the far camera centre."""
        g = torch.Generator().manual_seed(9)
        (c, P, X, L), _, exact = _near_tangent(40000, 1e-6, g)
        naive = float((_naive_hit(c, P, X, L) != exact).double().mean())
        cam = float((ray_sphere_intersections(c, X - c, P, L).hit != exact).double().mean())
        child = float((ray_sphere_intersections(X, X - c, P, L).hit != exact).double().mean())
        assert naive > 0.4
        assert child < 0.03 and child < cam / 3

    def test_feature_1e7_is_below_float32_resolution(self):
        """``|Delta| ~ 1e-7 L^2`` (float64 construction) is not resolvable in float32 at all:
        rounding the inputs to float32 alone changes the sign of their exact ``Delta`` in a
        large share of the cases. The stable form still beats the naive one on the float32
        inputs' exact sign."""
        g = torch.Generator().manual_seed(10)
        (c, P, X, L), built, exact = _near_tangent(40000, 1e-7, g)
        assert float((built != exact).double().mean()) > 0.2
        naive = float((_naive_hit(c, P, X, L) != exact).double().mean())
        child = float((ray_sphere_intersections(X, X - c, P, L).hit != exact).double().mean())
        assert child < naive / 3

    def test_exception(self):
        z = torch.zeros(3)
        with pytest.raises(ValueError, match="child"):
            flip_child(torch.ones(3), z, z)
        with pytest.raises(ValueError, match="parent"):
            flip_child(torch.ones(2), z, z)
        with pytest.raises(ValueError, match="camera_center"):
            flip_child(torch.ones(3), torch.ones(3), torch.full((3,), math.inf))
        with pytest.raises(ValueError, match="radius"):
            flip_child(torch.ones(3), torch.ones(3) * 2, z, length=-0.1)

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(11)
        c, P, X = _links(5, g)
        P.requires_grad_()
        X.requires_grad_()
        c.requires_grad_()
        assert torch.autograd.gradcheck(lambda p, x, cc: flip_child(p, x, cc)[0], (P, X, c))
        L = (X.detach() - P.detach()).norm(dim=-1).mul(1.05).requires_grad_()
        assert torch.autograd.gradcheck(lambda p, x, cc, ll: flip_child(p, x, cc, ll)[0],
                                        (P, X, c, L))


def test_docstring_examples():
    res = doctest.testmod(flips_module, extraglobs={"torch": torch})
    assert res.attempted > 0 and res.failed == 0
