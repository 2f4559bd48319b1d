"""The compile option of the silhouette and appearance terms: the compiled energy is the eager
one (to float32 round-off), with gradients for the differentiable versions, on a rig with and
without lens distortion, compiled into one graph (no host read left in the term)."""

from __future__ import annotations

import pytest
import torch
from torch._dynamo.utils import counters

from torchmocap.body import CapsuleBody
from torchmocap.cameras import CameraRig, make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import Poses
from torchmocap.likelihoods.appearance import AppearanceLikelihood
from torchmocap.likelihoods.silhouette import SilhouetteLikelihood, render_capsule_silhouettes
from torchmocap.skeleton import human31


@pytest.fixture(scope="module")
def scene():
    sk = human31()
    body = CapsuleBody(sk)
    ring = make_ring_rig(4).float()
    lens = CameraRig(ring.K, ring.R, ring.t, ring.image_size,
                     torch.tensor([-0.3, 0.13, 1e-3, -5e-4, 0.0]).expand(4, 5))
    th = sk.zero_pose()
    th[sk.dof_index("l_elbow_flex")] = 1.2
    th[sk.dof_index("r_hip_flex")] = 0.6
    masks = render_capsule_silhouettes(body, ring, th)
    g = torch.Generator().manual_seed(3)
    poses = th + 0.1 * torch.randn(48, sk.num_dofs, generator=g)
    imgs = (torch.rand(4, *masks.shape[1:], 3, generator=g) * 255).to(torch.uint8)
    imgs[masks] = torch.tensor([200, 40, 30], dtype=torch.uint8)
    return sk, body, ring, lens, masks, poses, imgs


def _energies(lik, frame, sk, poses):
    obs = lik.prepare(frame)
    return lik.energy(Poses(poses, sk), obs)


def test_compile_option_checked(scene):
    sk, body, ring, *_ = scene
    for cls in (SilhouetteLikelihood, AppearanceLikelihood):
        with pytest.raises(ValueError, match="compile: expected true or false"):
            cls(body, ring, compile="yes")
        assert "compile=True" in repr(cls(body, ring, compile=True))
        assert "compile" not in repr(cls(body, ring))


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["hard", "distance"])
def test_compiled_silhouette_is_the_eager_energy(scene, kind):
    """Compiles once or twice (~20-60 s each on a CPU)."""
    sk, body, ring, lens, masks, poses, _ = scene
    opts = {"hard": {}, "distance": dict(smooth=True, distance=1.0, reference_width=320)}[kind]
    frame = Frame(index=0, time=0.0, silhouettes=masks)
    for rig in ((ring, lens) if kind == "hard" else (lens,)):
        eager = SilhouetteLikelihood(body, rig, fg_samples=100, **opts)
        comp = SilhouetteLikelihood(body, rig, fg_samples=100, compile=True, **opts)
        counters.clear()
        x = poses.clone().requires_grad_(kind == "distance")
        got = _energies(comp, frame, sk, x)
        assert not counters["graph_break"], dict(counters["graph_break"])
        ref = _energies(eager, frame, sk, poses)
        assert float(ref.std()) > 0.01  # the poses differ: a real comparison
        torch.testing.assert_close(got.detach(), ref, atol=1e-5, rtol=0)
        if kind == "distance":
            xe = poses.clone().requires_grad_(True)
            _energies(eager, frame, sk, xe).sum().backward()
            got.sum().backward()
            torch.testing.assert_close(x.grad, xe.grad, atol=1e-4, rtol=1e-3)


@pytest.mark.slow
def test_compiled_appearance_is_the_eager_energy(scene):
    """Compiles once (~20-40 s on a CPU)."""
    sk, body, ring, lens, masks, poses, imgs = scene
    frame = Frame(index=0, time=0.0, images=imgs)
    eager = AppearanceLikelihood(body, lens, occlusion="outlier")
    comp = AppearanceLikelihood(body, lens, occlusion="outlier", compile=True)
    counters.clear()
    got = _energies(comp, frame, sk, poses)
    assert not counters["graph_break"], dict(counters["graph_break"])
    ref = _energies(eager, frame, sk, poses)
    assert float(ref.std()) > 1e-3
    torch.testing.assert_close(got, ref, atol=1e-5, rtol=0)
