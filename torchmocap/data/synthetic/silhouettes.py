"""Silhouette corruptions: boundary noise, holes, clutter blobs, floor shadows, dropped views.

All functions take and return boolean masks ``(B, H, W)`` (``B`` = frames × cameras flattened)
and draw every random number from the given ``torch.Generator``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "add_boundary_noise",
    "add_clutter",
    "dilate",
    "drop_views",
    "paint_ellipses",
    "punch_holes",
    "shadow_points",
]


def _rand(shape, generator: torch.Generator, device) -> Tensor:
    return torch.rand(shape, generator=generator, dtype=torch.float64).to(device)


def _poisson(rate: float, n: int, generator: torch.Generator) -> Tensor:
    """``(n,)`` Poisson counts via the generator (inversion; rates here are small)."""
    if rate <= 0:
        return torch.zeros(n, dtype=torch.long)
    u = torch.rand(n, generator=generator, dtype=torch.float64)
    k = torch.zeros(n, dtype=torch.long)
    p = torch.full((n,), float(torch.exp(torch.tensor(-rate, dtype=torch.float64))),
                   dtype=torch.float64)
    cdf = p.clone()
    for i in range(1, 64):
        more = u > cdf
        if not bool(more.any()):
            break
        k = k + more.long()
        p = p * rate / i
        cdf = cdf + p
    return k


def paint_ellipses(masks: Tensor, image: Tensor, cx: Tensor, cy: Tensor, rx: Tensor, ry: Tensor,
                   angle: Tensor, value: bool) -> Tensor:
    """Set the pixels of (rotated) filled ellipses to ``value`` (in place, returned).

    Args:
        masks: ``(B, H, W)`` bool.
        image, cx, cy, rx, ry, angle: ``(K,)`` image index, centre (px), semi-axes (px), rotation.
        value: True (add blobs) or False (punch holes).
    """
    if image.numel() == 0:
        return masks
    B, H, W = masks.shape
    dev = masks.device
    R = int(torch.ceil(torch.maximum(rx, ry).max()).item())
    off = torch.arange(-R, R + 1, device=dev, dtype=torch.float64)
    dy, dx = torch.meshgrid(off, off, indexing="ij")  # (G, G)
    x = torch.round(cx.to(dev))[:, None, None] + dx
    y = torch.round(cy.to(dev))[:, None, None] + dy
    ux, uy = x - cx.to(dev)[:, None, None], y - cy.to(dev)[:, None, None]
    c, s = torch.cos(angle.to(dev))[:, None, None], torch.sin(angle.to(dev))[:, None, None]
    a = (c * ux + s * uy) / rx.to(dev)[:, None, None]
    b = (-s * ux + c * uy) / ry.to(dev)[:, None, None]
    inside = (a * a + b * b <= 1) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
    img = image.to(dev)[:, None, None].expand_as(inside)
    loc = (img * H + y.long()) * W + x.long()
    masks.view(-1)[loc[inside]] = value
    return masks


def dilate(masks: Tensor, width: int) -> Tensor:
    """Binary dilation of ``(B, H, W)`` bool masks by a ``(2w+1)²`` square (shifted ORs)."""
    out = masks.clone()
    for i in range(1, width + 1):  # along x
        out[..., i:] |= masks[..., :-i]
        out[..., :-i] |= masks[..., i:]
    rows = out.clone()
    for i in range(1, width + 1):  # along y
        out[..., i:, :] |= rows[..., :-i, :]
        out[..., :-i, :] |= rows[..., i:, :]
    return out


def add_boundary_noise(masks: Tensor, prob: float, width: int, generator: torch.Generator
                       ) -> Tensor:
    """Flip pixels within ``width`` px of the contour with probability ``prob``.

    The band is ``dilate(m) & ~erode(m)`` (square structuring element); random numbers are
    drawn for band pixels only.
    """
    if prob <= 0:
        return masks
    band = dilate(masks, width) & dilate(~masks, width)
    idx = band.reshape(-1).nonzero().squeeze(-1)
    u = torch.rand(idx.shape[0], generator=generator, dtype=torch.float64).to(masks.device)
    out = masks.clone()
    flat = out.view(-1)
    sel = idx[u < prob]
    flat[sel] = ~flat[sel]
    return out


def punch_holes(masks: Tensor, rate: float, radius: tuple[float, float],
                generator: torch.Generator) -> Tensor:
    """Remove ``Poisson(rate)`` discs per image, centred on random foreground pixels."""
    B = masks.shape[0]
    counts = _poisson(rate, B, generator)
    fg = masks.reshape(B, -1).sum(-1).cpu()
    counts = torch.where(fg > 0, counts, torch.zeros_like(counts))
    K = int(counts.sum())
    u = torch.rand(K, generator=generator, dtype=torch.float64)
    r = radius[0] + (radius[1] - radius[0]) * torch.rand(K, generator=generator,
                                                         dtype=torch.float64)
    if K == 0:
        return masks
    image = torch.repeat_interleave(torch.arange(B), counts)
    # the floor(u·n_b)-th foreground pixel of image b
    flat = masks.reshape(B, -1).nonzero().cpu()  # sorted by image
    start = torch.cumsum(fg, 0) - fg
    pick = start[image] + (u * fg[image]).long().clamp(max=fg[image] - 1)
    pix = flat[pick, 1]
    W = masks.shape[-1]
    cx, cy = (pix % W).double(), torch.div(pix, W, rounding_mode="floor").double()
    return paint_ellipses(masks, image, cx, cy, r, r, torch.zeros(K, dtype=torch.float64), False)


def add_clutter(masks: Tensor, rate: float, radius: tuple[float, float],
                generator: torch.Generator) -> Tensor:
    """Add ``Poisson(rate)`` false-positive elliptic blobs per image at uniform positions."""
    B, H, W = masks.shape
    counts = _poisson(rate, B, generator)
    K = int(counts.sum())
    g = torch.rand(K, 5, generator=generator, dtype=torch.float64)
    if K == 0:
        return masks
    image = torch.repeat_interleave(torch.arange(B), counts)
    lo, hi = radius
    return paint_ellipses(masks, image, g[:, 0] * (W - 1), g[:, 1] * (H - 1),
                          lo + (hi - lo) * g[:, 2], lo + (hi - lo) * g[:, 3],
                          g[:, 4] * torch.pi, True)


def drop_views(masks: Tensor, prob: float, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Zero whole views with probability ``prob``; returns ``(masks, dropped (B,) bool)``."""
    dropped = torch.rand(masks.shape[0], generator=generator, dtype=torch.float64) < prob
    dropped = dropped.to(masks.device)
    if bool(dropped.any()):
        masks = masks.clone()
        masks[dropped] = False
    return masks, dropped


def shadow_points(points: Tensor, light_direction: Tensor, floor_z: float = 0.0) -> Tensor:
    """Project ``(*, N, 3)`` points onto the floor ``z = floor_z`` along the light direction.

    ``light_direction (3,)`` is the direction the light travels (negative z). Points below the
    floor stay where they are.
    """
    d = light_direction.to(points)
    if float(d[2]) >= 0:
        raise ValueError(f"light_direction: expected a negative z component, got {d.tolist()}")
    s = ((points[..., 2] - floor_z) / -d[2]).clamp_min(0)
    return points + s[..., None] * d
