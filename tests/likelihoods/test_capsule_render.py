"""render_capsule_silhouettes tests only the pixels in the box of a view's capsules: the same
masks as testing every pixel (an independent brute force over the whole image)."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import CameraRig, make_ring_rig
from torchmocap.likelihoods.silhouette import (
    _coverage_margin,
    _stadiums,
    render_capsule_silhouettes,
)
from torchmocap.skeleton import human31


def _every_pixel(body, rig, theta):
    st = _stadiums(body.endpoints(body.skeleton(theta[None])), body.radii, rig)
    sizes = rig.image_size.long()
    W, H = int(sizes[:, 0].max()), int(sizes[:, 1].max())
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    q = torch.stack([xs, ys], -1).reshape(1, -1, 2).to(st.ax.dtype)
    C = sizes.shape[0]
    out = (_coverage_margin(q.expand(C, -1, -1), st, smooth=False)[..., 0] > 0).view(C, H, W)
    for c, (w, h) in enumerate(sizes.tolist()):
        out[c, h:], out[c, :, w:] = False, False
    return out


def _rig():
    """Four views: two sizes, lens distortion, one camera looking away from the body and one
    so close that the body overflows its image."""
    ring = make_ring_rig(4, image_size=(160, 120))
    K, R, t = ring.K.clone(), ring.R.clone(), ring.t.clone()
    K[1, :2] *= 1.5  # camera 1: 240 x 180
    K[1, 0, 2], K[1, 1, 2] = 120.0, 90.0
    # camera 2 turned around its y axis: the body is behind it
    flip = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=R.dtype))
    R[2], t[2] = flip @ R[2], flip @ t[2]
    t[3, 2] -= 3.0  # camera 3 a metre from the body: it overflows the image
    size = torch.tensor([[160, 120], [240, 180], [160, 120], [160, 120]])
    dist = torch.tensor([[-0.2, 0.05, 1e-3, -1e-3, 0.0]], dtype=R.dtype).expand(4, 5).clone()
    return CameraRig(K, R, t, size, dist).float()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_masks_as_every_pixel(seed):
    sk = human31()
    body = CapsuleBody(sk).float()
    g = torch.Generator().manual_seed(seed)
    theta = sk.zero_pose(()).float()
    theta = theta + 0.3 * torch.randn(theta.shape, generator=g)
    theta[:3] = torch.tensor([0.1, -0.2, 0.9]) + 0.1 * torch.randn(3, generator=g)
    rig = _rig()
    fast = render_capsule_silhouettes(body, rig, theta, chunk=997)
    slow = _every_pixel(body, rig, theta)
    assert fast.shape == slow.shape == (4, 180, 240)
    assert torch.equal(fast, slow)
    counts = fast.flatten(1).sum(1)
    assert counts[0] > 100 and counts[1] > 100 and counts[2] == 0
    border = torch.cat([fast[3, 0, :160], fast[3, 119, :160], fast[3, :120, 0], fast[3, :120, 159]])
    assert counts[3] > counts[0] and bool(border.any())
