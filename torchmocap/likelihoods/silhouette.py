"""Multi-view silhouette likelihood of a capsule body (Pons-Moll et al. 2010, eq. 17, V_silh).

The energy is the disagreement between the projected model silhouette and the observed
foreground in *both* directions, normalised per view and averaged over views:

- model -> image: the fraction of the model's projected area that falls on background. Each
  capsule projects to a 2D "stadium" (its axis segment with a pixel radius ``f r / z`` at each
  end); a fixed grid of points inside every stadium is looked up in the mask, weighted by the
  stadium's area.
- image -> model: the fraction of foreground pixels not covered by any stadium, on a fixed,
  evenly spaced subset of ``G`` foreground pixels per view (chosen once per frame).

Both terms are batched over particles x views x capsules; no image is rendered, so the cost is
``O(P C B (m n + G))`` instead of ``O(P C H W)``. The *hard* version uses nearest-pixel lookups
and a 0/1 coverage test (fast, for sampling); the *smooth* version uses bilinear lookups of a
blurred mask and a sigmoid coverage of width ``tau`` pixels (differentiable, for gradient-based
optimisation). Shapes: ``P`` particles, ``C`` views, ``B`` capsules, ``G`` foreground samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "SilhouetteObservation",
    "SilhouetteLikelihood",
    "project_capsules",
    "silhouette_energy",
    "prepare_silhouettes",
    "render_capsule_silhouettes",
    "silhouette_iou",
]


@dataclass
class SilhouetteObservation:
    """Per-frame silhouette data prepared once and reused for every particle and layer.

    Attributes:
        masks: ``(C, H, W)`` float foreground in [0, 1] (hard lookups).
        blurred: ``(C, 1, H, W)`` blurred masks for the smooth version.
        fg_pixels: ``(C, G, 2)`` sampled foreground pixel centres (x, y).
        fg_valid: ``(C, G)`` which samples exist (views with fewer foreground pixels pad).
        view_valid: ``(C,)`` views to use (a dropped view or an empty mask is excluded).
    """

    masks: torch.Tensor
    blurred: torch.Tensor
    fg_pixels: torch.Tensor
    fg_valid: torch.Tensor
    view_valid: torch.Tensor


def prepare_silhouettes(masks: torch.Tensor, num_samples: int = 150, blur: float = 1.5,
                        view_valid: torch.Tensor | None = None,
                        dtype: torch.dtype = torch.float32) -> SilhouetteObservation:
    """Prepare ``masks (C, H, W)`` (bool or 0/1 or 0/255) for :func:`silhouette_energy`."""
    if not isinstance(masks, torch.Tensor) or masks.dim() != 3:
        raise ValueError(f"masks: expected a (C, H, W) tensor, got "
                         f"{getattr(masks, 'shape', type(masks).__name__)}")
    m = masks.to(dtype)
    if m.numel() and float(m.max()) > 1:
        m = m / 255.0
    m = (m > 0.5).to(dtype)
    C, H, W = m.shape
    valid = torch.ones(C, dtype=torch.bool) if view_valid is None else view_valid.bool().cpu()
    pix = torch.zeros(C, num_samples, 2, dtype=dtype)
    pv = torch.zeros(C, num_samples, dtype=torch.bool)
    for c in range(C):  # per view, once per frame (not per particle)
        ys, xs = torch.nonzero(m[c] > 0, as_tuple=True)
        n = xs.numel()
        if n == 0:
            valid[c] = False
            continue
        k = min(n, num_samples)
        idx = torch.linspace(0, n - 1, k).round().long()
        pix[c, :k, 0] = xs[idx].to(dtype) + 0.5
        pix[c, :k, 1] = ys[idx].to(dtype) + 0.5
        pv[c, :k] = True
    if blur > 0:
        r = max(1, int(round(3 * blur)))
        x = torch.arange(-r, r + 1, dtype=dtype)
        g = torch.exp(-0.5 * (x / blur) ** 2)
        g = g / g.sum()
        b = F.conv2d(m[:, None], g.view(1, 1, 1, -1), padding=(0, r))
        b = F.conv2d(b, g.view(1, 1, -1, 1), padding=(r, 0))
    else:
        b = m[:, None]
    return SilhouetteObservation(m.to(masks.device), b.to(masks.device), pix.to(masks.device),
                                 pv.to(masks.device), valid.to(masks.device))


def project_capsules(endpoints: torch.Tensor, radii: torch.Tensor, rig) -> tuple[torch.Tensor, ...]:
    """Project capsule axes ``(P, B, 2, 3)`` with radii ``(B,)`` into every camera.

    Returns ``ends (P, C, B, 2, 2)`` pixel endpoints, ``rpx (P, C, B, 2)`` pixel radii at both
    ends (``f r / z``), ``front (P, C, B)`` both ends in front of the camera.
    """
    P, B = endpoints.shape[:2]
    pix, depth, _ = rig.project(endpoints.reshape(P, B * 2, 3))
    C = pix.shape[1]
    ends = pix.reshape(P, C, B, 2, 2)
    z = depth.reshape(P, C, B, 2)
    K = rig.K.to(endpoints.dtype)
    f = 0.5 * (K[:, 0, 0] + K[:, 1, 1])  # (C,)
    front = (z > 1e-3).all(-1)
    r = radii.to(endpoints.dtype)[None, None, :, None]
    rpx = f[None, :, None, None] * r / z.clamp_min(1e-3)
    return ends, rpx, front


def _stadium_points(ends, rpx, m: int, n: int):
    """Grid of ``m x n`` points inside each projected capsule: ``(P, C, B, m*n, 2)``, and the
    stadium areas ``(P, C, B)``. Computed on x and y planes (one pass per term)."""
    dt = ends.dtype
    t = torch.linspace(0, 1, m, dtype=dt, device=ends.device)
    s = torch.linspace(-0.75, 0.75, n, dtype=dt, device=ends.device)
    T = t.repeat_interleave(n)  # (m*n,)
    S = s.repeat(m)
    ax, ay = ends[..., 0, 0, None], ends[..., 0, 1, None]
    dx = ends[..., 1, 0, None] - ax
    dy = ends[..., 1, 1, None] - ay
    L = torch.sqrt((dx * dx + dy * dy).clamp_min(1e-12))  # finite gradient for point-like
    inv = 1.0 / L.clamp_min(1e-6)
    ux = torch.where(L > 1e-6, dx * inv, torch.ones_like(dx))
    uy = dy * inv
    r0, r1 = rpx[..., 0, None], rpx[..., 1, None]
    off = (r0 + (r1 - r0) * T) * S  # (P, C, B, m*n) signed offset along the normal
    px = ax + dx * T - uy * off
    py = ay + dy * T + ux * off
    area = L[..., 0] * (rpx[..., 0] + rpx[..., 1]) + torch.pi * rpx.pow(2).mean(-1)
    return torch.stack([px, py], -1), area


def _lookup_nearest(masks, pts):
    """Mask values at ``pts (P, C, N, 2)`` (0 outside the image): ``(P, C, N)``."""
    C, H, W = masks.shape
    x = pts[..., 0].floor().long()
    y = pts[..., 1].floor().long()
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    cam = (torch.arange(C, device=pts.device) * (H * W))[None, :, None]
    idx = cam + y.clamp(0, H - 1) * W + x.clamp(0, W - 1)  # (P, C, N)
    vals = masks.reshape(-1)[idx.reshape(-1)].reshape(idx.shape)
    return vals * inside.to(vals.dtype)


def _lookup_bilinear(blurred, pts):
    C, _, H, W = blurred.shape
    P, _, N, _ = pts.shape
    g = torch.stack([pts[..., 0] / W * 2 - 1, pts[..., 1] / H * 2 - 1], -1)  # (P, C, N, 2)
    g = g.permute(1, 0, 2, 3)  # (C, P, N, 2)
    v = F.grid_sample(blurred, g, mode="bilinear", padding_mode="zeros", align_corners=False)
    return v[:, 0].permute(1, 0, 2)  # (P, C, N)


def _coverage_margin(q, ends, rpx, smooth: bool):
    """Largest coverage margin of pixels ``q (C, G, 2)`` over the stadiums ``ends (P, C, B, 2, 2)``
    with end radii ``rpx (P, C, B, 2)``: ``(P, C, G)``, positive inside the model silhouette.

    Written on scalar planes (x and y separately, squared distances) so every step is one
    elementwise pass over ``P*C*G*B`` values: this is the hot loop of the likelihood.
    """
    ax = ends[..., 0, 0][:, :, None]  # (P, C, 1, B)
    ay = ends[..., 0, 1][:, :, None]
    dx = (ends[..., 1, 0] - ends[..., 0, 0])[:, :, None]
    dy = (ends[..., 1, 1] - ends[..., 0, 1])[:, :, None]
    dd = (dx * dx + dy * dy).clamp_min(1e-9)
    wx = q[None, :, :, None, 0] - ax  # (P, C, G, B)
    wy = q[None, :, :, None, 1] - ay
    wd = wx * dx + wy * dy
    t = (wd / dd).clamp(0, 1)
    r0 = rpx[..., 0][:, :, None]
    r1 = rpx[..., 1][:, :, None]
    if smooth:  # out-of-place: autograd needs the intermediates
        dist2 = wx * wx + wy * wy - t * (2 * wd - t * dd)
        r = r0 + t * (r1 - r0)
        return (r - dist2.clamp_min(1e-12).sqrt()).max(-1).values
    dist2 = wx.mul_(wx).add_(wy.mul_(wy)).sub_(t * (2 * wd - t * dd))
    r = t.mul_(r1 - r0).add_(r0)
    return r.mul_(r).sub_(dist2).max(-1).values


def silhouette_energy(endpoints: torch.Tensor, radii: torch.Tensor, rig,
                      obs: SilhouetteObservation, smooth: bool = False, axis_samples: int = 5,
                      across_samples: int = 3, tau: float = 1.5) -> torch.Tensor:
    """Silhouette disagreement ``V_silh (P,)`` in [0, 1] of capsules ``endpoints (P, B, 2, 3)``.

    0 means the projected capsules and the foreground agree exactly at the sampled points; see
    the module docstring for the two terms.
    """
    ends, rpx, front = project_capsules(endpoints, radii, rig)
    pts, area = _stadium_points(ends, rpx, axis_samples, across_samples)
    P, C, B = area.shape
    pts = pts.reshape(P, C, -1, 2)
    if smooth:
        inside = _lookup_bilinear(obs.blurred.to(pts.dtype), pts)
    else:
        inside = _lookup_nearest(obs.masks.to(pts.dtype), pts)
    inside = inside.reshape(P, C, B, -1).mean(-1)  # fraction of each stadium on foreground
    w = area * front.to(area.dtype)
    m2i = 1 - (inside * w).sum(-1) / w.sum(-1).clamp_min(1e-9)  # (P, C)

    # capsules behind a camera get a negative radius: they cover nothing
    rpx = torch.where(front[..., None], rpx, torch.full_like(rpx, -1e3))
    margin = _coverage_margin(obs.fg_pixels.to(pts.dtype), ends, rpx, smooth)  # (P, C, G)
    if smooth:
        covered = torch.sigmoid(margin / tau)
    else:
        covered = (margin > 0).to(margin.dtype)
    fv = obs.fg_valid.to(margin.dtype)
    i2m = 1 - (covered * fv).sum(-1) / fv.sum(-1).clamp_min(1)  # (P, C)

    vv = obs.view_valid.to(margin.dtype)
    per_view = 0.5 * (m2i + i2m)
    return (per_view * vv).sum(-1) / vv.sum().clamp_min(1)


class SilhouetteLikelihood(nn.Module):
    """Log-likelihood ``-weight * V_silh`` of poses given multi-view silhouettes.

    Args:
        body: a :class:`~torchmocap.body.CapsuleBody` (its skeleton does the FK).
        rig: the :class:`~torchmocap.cameras.CameraRig` of the masks.
        weight: ``lambda_1`` of Pons-Moll eq. 17 (2 in the paper).
        smooth: differentiable variant (bilinear lookups, sigmoid coverage).

    ``forward(theta (P, D), obs) -> (P,)`` with ``obs`` from :func:`prepare_silhouettes`.
    """

    def __init__(self, body, rig, weight: float = 2.0, smooth: bool = False,
                 axis_samples: int = 5, across_samples: int = 3, tau: float = 1.5):
        super().__init__()
        self.body = body
        self.rig = rig
        self.weight = float(weight)
        self.smooth = smooth
        self.axis_samples = axis_samples
        self.across_samples = across_samples
        self.tau = tau

    def energy(self, theta: torch.Tensor, obs: SilhouetteObservation) -> torch.Tensor:
        kin = self.body.skeleton(theta, check_finite=False)
        ep = self.body.endpoints(kin)
        return silhouette_energy(ep, self.body.radii, self.rig, obs, self.smooth,
                                 self.axis_samples, self.across_samples, self.tau)

    def forward(self, theta: torch.Tensor, obs: SilhouetteObservation) -> torch.Tensor:
        return -self.weight * self.energy(theta, obs)


def render_capsule_silhouettes(body, rig, theta: torch.Tensor, chunk: int = 20000
                               ) -> torch.Tensor:
    """Exact capsule-model silhouettes ``(C, H, W)`` bool of one pose ``theta (D,)``.

    Every pixel centre is tested against every projected capsule (the same stadium model the
    likelihood uses), in chunks of pixels. Used for overlays, IoU reports and test oracles.
    """
    ep = body.endpoints(body.skeleton(theta[None]))
    ends, rpx, front = project_capsules(ep, body.radii, rig)
    rpx = torch.where(front[..., None], rpx, torch.full_like(rpx, -1e3))
    sizes = {tuple(int(v) for v in s) for s in rig.image_size.tolist()}
    if len(sizes) != 1:
        raise ValueError(f"rig: all cameras need one image size, got {sorted(sizes)}")
    W, H = sizes.pop()
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    q = torch.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2).to(ep.dtype)
    C = ends.shape[1]
    out = torch.empty(C, H * W, dtype=torch.bool)
    for a in range(0, H * W, chunk):
        qq = q[a:a + chunk][None].expand(C, -1, -1)
        out[:, a:a + chunk] = _coverage_margin(qq, ends, rpx, smooth=False)[0] > 0
    return out.reshape(C, H, W)


def silhouette_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-view intersection over union of boolean masks ``(C, H, W)``: ``(C,)``."""
    a, b = a.bool(), b.bool()
    inter = (a & b).flatten(1).sum(-1).double()
    union = (a | b).flatten(1).sum(-1).double()
    return inter / union.clamp_min(1)
