"""Multi-view silhouette likelihood of a capsule body (Pons-Moll et al. 2010, eq. 17, V_silh).

The energy is the disagreement between the projected model silhouette and the observed
foreground in *both* directions, normalised per view and averaged over views:

- model -> image: the fraction of the model's projected area that falls on background. Each
  capsule projects to a 2D "stadium" (its axis segment with a pixel radius ``f r / z`` at each
  end); a fixed grid of points inside every stadium is looked up in the mask, weighted by the
  stadium's area.
- image -> model: the fraction of foreground pixels not covered by any stadium, on a fixed,
  evenly spaced subset of ``G`` foreground pixels per view (chosen once per frame).

The *distance* version (``distance=s`` pixels) replaces both 0/1 tests by a robust distance:
a model point costs ``rho(d)`` with ``d`` its distance (pixels, from the masks' Euclidean distance
transform, bilinear) to the nearest foreground pixel, a foreground sample ``rho(d)`` with ``d``
how far it lies outside every stadium, ``rho(d) = d^2 / (d^2 + s^2)`` (Geman-McClure: 0 at 0, 1/2
at ``s``, towards 1 far away). It is differentiable and zero where model and masks agree, so
its minimum sits at the pose that generated the masks: the blurred version is not, since a
blurred mask reads < 1 near every edge and a limb drawn inside the torso's silhouette pays less
than the true one along its own edge (measured on the own-capsule control: 0.16 at the true
pose, and lower for an arm folded into the torso).

Both terms are batched over particles x views x capsules; no image is rendered, so the cost is
``O(P C B (m n + G))`` instead of ``O(P C H W)``. The *hard* version uses nearest-pixel lookups
and a 0/1 coverage test (fast, for sampling); the *smooth* version uses bilinear lookups of a
blurred mask and a sigmoid coverage of width ``tau`` pixels (differentiable, for gradient-based
optimisation). Pixel ``(x, y)`` covers ``[x - 0.5, x + 0.5) x [y - 0.5, y + 0.5)``, as in
:mod:`torchmocap.cameras` and the synthesis rasteriser. Internally the projected capsules are
``(C, B, P)`` planes, particles innermost. Shapes: ``P`` particles, ``C`` views, ``B`` capsules,
``G`` foreground samples.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F

from torchmocap.compilation import CompiledFunction
from torchmocap.likelihoods.base import Likelihood, blockwise, check_block

__all__ = [
    "SilhouetteObservation",
    "SilhouetteLikelihood",
    "silhouette_energy",
    "prepare_silhouettes",
    "render_capsule_silhouettes",
    "MIN_PLAUSIBLE_IOU",
    "check_fit_iou",
    "silhouette_iou",
    "soft_capsule_silhouettes",
]

#: a body fitted to a person's masks overlaps them with IoU 0.5-0.8 (capsules vs the skinned
#: mesh 0.77; the real bodytrack frame 0.5-0.6); below this the masks or the cameras are wrong
MIN_PLAUSIBLE_IOU = 0.3


@dataclass
class SilhouetteObservation:
    """Per-frame silhouette data prepared once and reused for every particle and layer.

    Attributes:
        masks: ``(C, H, W)`` float foreground in {0, 1}.
        padded: ``(C, H+2, W+2)`` uint8 0/1: the masks with a one-pixel zero border (hard
            lookups; a quarter of the float masks' size, so the lookups stay in the caches).
        blurred: ``(C, 1, H, W)`` blurred masks for the smooth version.
        fg_pixels: ``(C, G, 2)`` sampled foreground pixel centres (x, y); pixel ``x`` covers
            ``[x - 0.5, x + 0.5)`` (the convention of the cameras and the rasteriser).
        fg_valid: ``(C, G)`` which samples exist (views with fewer foreground pixels pad).
        view_valid: ``(C,)`` views to use (a dropped view or an empty mask is excluded).
        outside: ``(C, 1, H, W)`` distance (pixels) of each pixel centre to the nearest
            foreground pixel centre (0 on the foreground), for the distance version; ``None``
            unless prepared with ``distance=True``.
    """

    masks: torch.Tensor
    padded: torch.Tensor
    blurred: torch.Tensor
    fg_pixels: torch.Tensor
    fg_valid: torch.Tensor
    view_valid: torch.Tensor
    outside: torch.Tensor | None = None


def prepare_silhouettes(masks: torch.Tensor, num_samples: int = 150,
                        blur: float | Sequence[float] | torch.Tensor = 1.5,
                        view_valid: torch.Tensor | None = None,
                        dtype: torch.dtype = torch.float32,
                        distance: bool = False) -> SilhouetteObservation:
    """Prepare ``masks (C, H, W)`` for :func:`silhouette_energy` (``distance``: also the
    distance transform of the background, for the distance version; ``blur``: the mask blur's
    std in pixels, one number or one per view).

    The mask contract (foreground = 1): ``bool``; any numeric dtype whose values are exactly
    0 and 1; or ``uint8`` whose values are exactly 0 and 255 (8-bit image files). Anything else
    — soft or blurred masks (0.5, 1.196), 0/255 in another dtype, labels (2), NaN or infinity —
    is a ``ValueError`` naming ``masks`` and the values found: a silent threshold would read
    such masks wrongly. Threshold soft masks yourself (``masks > 0.5``). The check is one
    reduction over the masks (they are prepared once per frame).
    """
    if not isinstance(masks, torch.Tensor) or masks.dim() != 3:
        raise ValueError(f"masks: expected a (C, H, W) tensor, got "
                         f"{getattr(masks, 'shape', type(masks).__name__)}")
    if masks.dtype == torch.bool:
        m = masks.to(dtype)
    else:
        if masks.is_complex():
            raise ValueError(f"masks: expected a bool mask, 0/1 values or uint8 0/255; found "
                             f"dtype {masks.dtype}")
        one = 255 if masks.dtype == torch.uint8 else 1
        # all values 0 or `one` (uint8: 0/1 or 0/255, not mixed); NaN and inf fail both tests
        top = masks.amax() if masks.numel() else None
        if top is not None:
            top_v = top.item()
            if top_v not in (0, 1, one) or not bool(((masks == 0) | (masks == top)).all()):
                vals = torch.unique(masks.detach().flatten().cpu())
                shown = ", ".join(f"{v:g}" for v in vals[:8].tolist())
                more = f", ... ({vals.numel()} distinct)" if vals.numel() > 8 else ""
                hint = "" if masks.dtype == torch.uint8 or top_v != 255 else \
                    "; 0/255 is read as uint8 only"
                raise ValueError(f"masks: expected a bool mask, 0/1 values or uint8 0/255; "
                                 f"found values {{{shown}{more}}} ({masks.dtype}){hint}")
        m = (masks != 0).to(dtype)
    C, H, W = m.shape
    dev = masks.device
    valid = torch.ones(C, dtype=torch.bool, device=dev) if view_valid is None \
        else view_valid.bool().to(dev)
    pix = torch.zeros(C, num_samples, 2, dtype=dtype, device=dev)
    pv = torch.zeros(C, num_samples, dtype=torch.bool, device=dev)
    for c in range(C):  # per view, once per frame (not per particle)
        ys, xs = torch.nonzero(m[c] > 0, as_tuple=True)
        n = xs.numel()
        if n == 0:
            valid[c] = False
            continue
        k = min(n, num_samples)
        idx = torch.linspace(0, n - 1, k, device=dev).round().long()
        pix[c, :k, 0] = xs[idx].to(dtype)  # pixel centres sit at integer coordinates
        pix[c, :k, 1] = ys[idx].to(dtype)
        pv[c, :k] = True
    if isinstance(blur, torch.Tensor):  # (a host copy: pass numbers in a hot path)
        blurs = [float(v) for v in blur.detach().flatten().tolist()]
    elif isinstance(blur, (int, float)):
        blurs = [float(blur)]
    else:
        blurs = [float(v) for v in blur]
    if len(blurs) not in (1, C):
        raise ValueError(f"blur: expected a number or one value per view ({C}), got "
                         f"{len(blurs)} values")
    if len(set(blurs)) == 1:
        b = _blur(m[:, None], blurs[0])
    else:  # per-view widths (views of different resolutions)
        b = torch.cat([_blur(m[c:c + 1, None], blurs[c]) for c in range(C)])
    outside = _outside_distance(m).to(dev) if distance else None
    padded = F.pad((m != 0).to(torch.uint8), (1, 1, 1, 1))
    return SilhouetteObservation(m.to(dev), padded.to(dev), b.to(dev),
                                 pix.to(dev), pv.to(dev), valid.to(dev), outside)


def _blur(m: torch.Tensor, std: float) -> torch.Tensor:
    """Separable Gaussian blur (std in pixels; 0 = none) of masks ``m (C, 1, H, W)``."""
    if std <= 0:
        return m
    r = max(1, int(round(3 * std)))
    x = torch.arange(-r, r + 1, dtype=m.dtype, device=m.device)
    g = torch.exp(-0.5 * (x / std) ** 2)
    g = g / g.sum()
    b = F.conv2d(m, g.view(1, 1, 1, -1), padding=(0, r))
    return F.conv2d(b, g.view(1, 1, -1, 1), padding=(r, 0))


def _outside_distance(m: torch.Tensor) -> torch.Tensor:
    """Exact Euclidean distance (pixels) of every pixel of ``m (C, H, W)`` to the nearest
    foreground pixel, ``(C, 1, H, W)``: 0 on the foreground; a view without foreground reads
    ``H + W``. Separable and on ``m``'s device (no host round trip): the distance along each
    row from running indices, then ``min_y' (g(y', x)^2 + (y - y')^2)`` down each column, one
    in-place pass per row offset. The squared distances are exact integers; the root is taken
    in float64 (the value scipy's ``distance_transform_edt`` gives, to the last bit)."""
    C, H, W = m.shape
    dev = m.device
    fg = m > 0
    big = H + W
    idx = torch.arange(W, device=dev).expand(C, H, W)
    last = torch.where(fg, idx, -big).cummax(-1).values
    nxt = torch.where(fg, idx, 2 * big).flip(-1).cummin(-1).values.flip(-1)
    g = torch.minimum(idx - last, nxt - idx).clamp_max(big).to(torch.float32)
    g2 = g * g  # exact integers in float32 (below 2^24 for images up to ~2900 pixels a side)
    out = g2.clone()
    for d in range(1, H):
        torch.minimum(out[:, d:], g2[:, :-d] + d * d, out=out[:, d:])
        torch.minimum(out[:, :-d], g2[:, d:] + d * d, out=out[:, :-d])
    return out.double().sqrt().to(m.dtype)[:, None]


def _robust(d: torch.Tensor, scale) -> torch.Tensor:
    """Geman-McClure ``d^2 / (d^2 + scale^2)`` of distances ``d >= 0`` (pixels); ``scale`` a
    number or a per-view ``(C,)`` tensor (``d`` view-first)."""
    scale = _per_view(scale, d)
    d2 = d * d
    return d2 / (d2 + scale * scale)


def _per_view(v, like: torch.Tensor):
    """A number as it is; a per-view ``(C,)`` tensor shaped to broadcast over ``like (C, ...)``."""
    if isinstance(v, torch.Tensor):
        return v.to(like).view(-1, *([1] * (like.dim() - 1)))
    return v


def _lookup_distance(outside: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Distance to the foreground at pixels ``px, py (C, ...)``: bilinear inside the image; a
    point outside adds its distance to the image's border to the border's value (continuous,
    an upper bound of the Euclidean distance)."""
    C, _, H, W = outside.shape
    cx = px.clamp(0, W - 1)
    cy = py.clamp(0, H - 1)
    g = torch.stack([(cx + 0.5) / W * 2 - 1, (cy + 0.5) / H * 2 - 1], -1).reshape(C, -1, 1, 2)
    v = F.grid_sample(outside.to(px.dtype), g, mode="bilinear", padding_mode="border",
                      align_corners=False).view(px.shape)
    ox, oy = px - cx, py - cy
    beyond = (ox * ox + oy * oy).clamp_min(1e-12).sqrt()
    return v + torch.where((ox != 0) | (oy != 0), beyond, torch.zeros_like(beyond))


class _Stadiums(NamedTuple):
    """Projected capsules as ``(C, B, P)`` planes (particles innermost): first end ``(ax, ay)``,
    axis ``(dx, dy)``, its length ``L``, unit direction ``(ex, ey)``, ``inv = 1/L`` (0 for
    point-like stadiums), end radii ``r0, r1`` in pixels. Capsules with an end behind the
    camera sit far outside every image with zero radius, so they cover no pixel."""

    ax: torch.Tensor
    ay: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor
    L: torch.Tensor
    ex: torch.Tensor
    ey: torch.Tensor
    inv: torch.Tensor
    r0: torch.Tensor
    r1: torch.Tensor


def _stadiums(endpoints: torch.Tensor, radii: torch.Tensor, rig,
              distorted: bool | None = None) -> _Stadiums:
    """:class:`_Stadiums` of capsule axes ``endpoints (P, B, 2, 3)`` with radii ``(B,)``
    (``distorted``: the rig's :attr:`~torchmocap.cameras.CameraRig.has_distortion`, when
    known)."""
    P, B = endpoints.shape[:2]
    dt = endpoints.dtype
    pts = endpoints.permute(2, 1, 0, 3).reshape(2 * B * P, 3)  # (end, B, P) order
    u, v, depth, _ = rig.project_planar(pts, visibility=False, distorted=distorted)  # (C, 2BP)
    C = u.shape[0]
    pix = torch.stack([u, v], 1).view(C, 2, 2, B, P).transpose(1, 2)  # (C, end, xy, B, P)
    z = depth.view(C, 2, B, P)
    K = rig.K.to(dt)
    f = 0.5 * (K[:, 0, 0] + K[:, 1, 1])  # (C,)
    front = (z > 1e-3).all(1)  # (C, B, P)
    rpx = (f[:, None, None, None] * radii.to(dt)[None, None, :, None]) / z.clamp_min(1e-3)
    far = torch.full((), -1e7, dtype=dt, device=pix.device)
    zero = torch.zeros((), dtype=dt, device=pix.device)
    ax = torch.where(front, pix[:, 0, 0], far)
    ay = torch.where(front, pix[:, 0, 1], far)
    dx = torch.where(front, pix[:, 1, 0], far) - ax
    dy = torch.where(front, pix[:, 1, 1], far) - ay
    r0 = torch.where(front, rpx[:, 0], zero)
    r1 = torch.where(front, rpx[:, 1], zero)
    L = torch.sqrt((dx * dx + dy * dy).clamp_min(1e-12))  # finite gradient for point-like
    long = L > 1e-6
    inv = torch.where(long, 1.0 / L.clamp_min(1e-6), zero)
    ex = torch.where(long, dx * inv, torch.ones((), dtype=dt, device=pix.device))
    ey = dy * inv
    return _Stadiums(ax, ay, dx, dy, torch.where(long, L, zero), ex, ey, inv, r0, r1)


def _stadium_points(st: _Stadiums, m: int, n: int) -> tuple[torch.Tensor, ...]:
    """Grid of ``m x n`` points inside each stadium, ``px, py (C, m*n, B, P)``, and the stadium
    areas ``(C, B, P)``."""
    dt = st.ax.dtype
    t = torch.linspace(0, 1, m, dtype=dt, device=st.ax.device)
    s = torch.linspace(-0.75, 0.75, n, dtype=dt, device=st.ax.device)
    T = t.repeat_interleave(n)[None, :, None, None]  # (1, m*n, 1, 1)
    S = s.repeat(m)[None, :, None, None]
    ax, ay, dx, dy, r0 = (x[:, None] for x in (st.ax, st.ay, st.dx, st.dy, st.r0))
    # signed offset along the normal (-ey, ex): (r0 + (r1 - r0) t) s
    off = torch.addcmul(r0 * S, (st.r1 - st.r0)[:, None], T * S)
    px = torch.addcmul(ax, dx, T).addcmul_(st.ey[:, None], off, value=-1)
    py = torch.addcmul(ay, dy, T).addcmul_(st.ex[:, None], off)
    area = st.L * (st.r0 + st.r1) + (torch.pi / 2) * (st.r0 * st.r0 + st.r1 * st.r1)
    return px, py, area


def _lookup_nearest(padded: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Mask values (0/1 in ``px``'s dtype) at pixels ``px, py (C, ...)`` from
    ``padded (C, H+2, W+2)`` (any dtype; the mask with a one-pixel zero border: points outside
    the image read 0)."""
    C, H2, W2 = padded.shape
    dt = px.dtype
    if padded.numel() >= 2**24 and px.dtype != torch.float64:  # float32 indices stay exact
        px, py = px.double(), py.double()
    lead = (C,) + (1,) * (px.dim() - 1)
    base = (torch.arange(C, device=px.device, dtype=px.dtype) * (H2 * W2) + W2 + 1).view(lead)
    # pixel x covers [x - 0.5, x + 0.5) (the cameras' and the rasteriser's convention)
    x = (px + 0.5).clamp_(-1, W2 - 2).floor_()
    y = (py + 0.5).clamp_(-1, H2 - 2).floor_()
    idx = torch.addcmul(x.add_(base), y, torch.full((), W2, dtype=px.dtype, device=px.device))
    return padded.reshape(-1)[idx.long().reshape(-1)].view(px.shape).to(dt)


def _lookup_bilinear(blurred: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Bilinear values of ``blurred (C, 1, H, W)`` at pixels ``px, py (C, ...)`` (0 outside)."""
    C, _, H, W = blurred.shape
    # align_corners=False puts pixel i's centre at (i + 0.5) / W * 2 - 1
    g = torch.stack([(px + 0.5) / W * 2 - 1, (py + 0.5) / H * 2 - 1], -1).reshape(C, -1, 1, 2)
    v = F.grid_sample(blurred, g, mode="bilinear", padding_mode="zeros", align_corners=False)
    return v.view(px.shape)


def _coverage_margin(q: torch.Tensor, st: _Stadiums, smooth: bool) -> torch.Tensor:
    """Largest coverage margin of pixels ``q (C, G, 2)`` over the stadiums ``st``: ``(C, G, P)``,
    positive inside the model silhouette (``r(t)^2 - d^2`` for the hard test, ``r(t) - d`` in
    pixels when ``smooth``).

    A stadium is the set of pixels within ``r(t) = r0 + t (r1 - r0)`` of its axis segment, ``t``
    the clamped position of the closest axis point. Both coordinates of every pixel in every
    stadium's frame (along the unit axis, and across it) come out of one matrix product of
    homogeneous pixels with per-stadium coefficients; the rest is six elementwise passes over
    ``G B P`` values per view, particles innermost (the reduction over ``B`` then runs over an
    outer dimension, which vectorises). This is the hot loop of the likelihood.
    """
    C, G = q.shape[:2]
    dt = st.ax.dtype
    B, P = st.ax.shape[1:]
    # coefficients of (qx, qy, 1) for the along / across coordinates: (C, 3, 2 B P)
    coef = torch.stack([torch.stack([st.ex, st.ey, -(st.ax * st.ex + st.ay * st.ey)], 1),
                        torch.stack([-st.ey, st.ex, st.ax * st.ey - st.ay * st.ex], 1)],
                       2).reshape(C, 3, -1)
    qh = torch.cat([q.to(dt), torch.ones(C, G, 1, dtype=dt, device=q.device)], -1)
    r0 = st.r0[:, None]  # (C, 1, B, P)
    slope = ((st.r1 - st.r0) * st.inv)[:, None]
    Lb = st.L[:, None]
    if smooth:  # out-of-place, all views at once: autograd needs the intermediates
        sp = torch.bmm(qh, coef).view(C, G, 2, B, P)
        s, perp = sp[:, :, 0], sp[:, :, 1]  # (C, G, B, P)
        sc = torch.clamp(s, min=torch.zeros_like(Lb), max=Lb)
        r = torch.addcmul(r0, sc, slope)
        along = s - sc
        d2 = along * along + perp * perp
        return (r - d2.clamp_min(1e-12).sqrt()).amax(2)
    # one view at a time: blocks of G B P values stay cache-sized (and out of the allocator's
    # slow path for multi-megabyte temporaries)
    m = torch.empty(C, G, P, dtype=dt, device=q.device)
    for c in range(C):
        sp = torch.mm(qh[c], coef[c]).view(G, 2, B, P)
        s, perp = sp[:, 0], sp[:, 1]  # (G, B, P)
        sc = torch.clamp(s, min=torch.zeros_like(Lb[c]), max=Lb[c])
        r = torch.addcmul(r0[c], sc, slope[c])
        d2 = (s - sc).square_().addcmul_(perp, perp)
        torch.amin(d2.addcmul_(r, r, value=-1), 1, out=m[c])
    return m.neg_()


def silhouette_energy(endpoints: torch.Tensor, radii: torch.Tensor, rig,
                      obs: SilhouetteObservation, smooth: bool = False, axis_samples: int = 5,
                      across_samples: int = 3, tau: float | torch.Tensor = 1.5,
                      distance: float | torch.Tensor | None = None,
                      distorted: bool | None = None) -> torch.Tensor:
    """Silhouette disagreement ``V_silh (P,)`` in [0, 1] of capsules ``endpoints (P, B, 2, 3)``.

    0 means the projected capsules and the foreground agree exactly at the sampled points; see
    the module docstring for the two terms and the three versions (hard; ``smooth``;
    ``distance``, the robust scale in pixels, which needs ``obs`` prepared with
    ``distance=True``). ``tau`` and ``distance`` are numbers or per-view ``(C,)`` tensors.
    Without any usable view (all dropped or empty) every particle gets 1: the frame carries no
    silhouette evidence, and it must not look like a perfect match. ``distorted``: the rig's
    ``has_distortion`` when the caller has read it (no host read of tensor values is left
    then, so the function compiles into one graph).
    """
    st = _stadiums(endpoints, radii, rig, distorted)
    dt = st.ax.dtype
    px, py, area = _stadium_points(st, axis_samples, across_samples)
    if distance is not None:
        if obs.outside is None:
            raise ValueError("obs: the distance version needs prepare_silhouettes(..., "
                             "distance=True)")
        cost = _robust(_lookup_distance(obs.outside, px, py), distance).mean(1)  # (C, B, P)
        m2i = (cost * area).sum(1) / area.sum(1).clamp_min(1e-9)
        margin = _coverage_margin(obs.fg_pixels, st, True)  # (C, G, P), pixels
        uncovered = _robust(torch.relu(-margin), distance)
        fv = obs.fg_valid.to(dt)[..., None]
        i2m = (uncovered * fv).sum(1) / fv.sum(1).clamp_min(1)
        return _over_views(m2i, i2m, obs.view_valid)
    if smooth:
        inside = _lookup_bilinear(obs.blurred.to(dt), px, py)
    else:
        inside = _lookup_nearest(obs.padded, px, py)
    inside = inside.mean(1)  # (C, B, P) fraction of each stadium on foreground
    m2i = 1 - (inside * area).sum(1) / area.sum(1).clamp_min(1e-9)  # (C, P)

    margin = _coverage_margin(obs.fg_pixels, st, smooth)  # (C, G, P)
    if smooth:
        covered = torch.sigmoid(margin / _per_view(tau, margin))
    else:
        covered = (margin > 0).to(dt)
    fv = obs.fg_valid.to(dt)[..., None]  # (C, G, 1)
    i2m = 1 - (covered * fv).sum(1) / fv.sum(1).clamp_min(1)  # (C, P)
    return _over_views(m2i, i2m, obs.view_valid)


def _over_views(m2i: torch.Tensor, i2m: torch.Tensor, view_valid: torch.Tensor) -> torch.Tensor:
    """``V_silh (P,)``: the mean over usable views of ``(m2i + i2m) / 2`` (each ``(C, P)``); 1
    for every particle without any usable view (uninformative, never a perfect 0)."""
    vv = view_valid.to(m2i.dtype)[:, None]
    n = vv.sum()
    mean = (0.5 * (m2i + i2m) * vv).sum(0) / n.clamp_min(1)
    return torch.where(n > 0, mean, torch.ones_like(mean))


class SilhouetteLikelihood(Likelihood):
    """Silhouette energy ``V_silh`` (eq. 17) of a capsule body against multi-view masks.

    Args:
        body: the :class:`~torchmocap.body.CapsuleBody` of the subject.
        rig: the :class:`~torchmocap.cameras.CameraRig` of the masks.
        smooth: differentiable variant (bilinear lookups of blurred masks, sigmoid coverage),
            for gradient-based optimisation; the hard variant is faster (for sampling).
        fg_samples: ``G`` foreground pixels per view for the image -> model term.
        blur: std (pixels) of the mask blur of the smooth variant (default 1.5 when smooth).
        axis_samples, across_samples: grid of points inside each projected capsule.
        tau: width (pixels) of the smooth coverage test.
        distance: robust scale (pixels) of the distance version (differentiable, zero where
            model and masks agree; see the module docstring); needs ``smooth=True``, and then
            replaces the blurred lookups and the sigmoid coverage. ``None``: not used.
        reference_width: the image width (pixels) that ``blur``, ``tau`` and ``distance`` are
            given for: each view scales them by its own width / ``reference_width``, so the term
            tolerates the same fraction of the image at any resolution (the presets give them
            for 320-pixel-wide views). ``None``: raw pixels in every view.
        compile: run the energy through ``torch.compile`` (:mod:`torchmocap.compilation`:
            the first call compiles, then ~3x faster on a CPU; not bit-identical to the eager
            energy, falls back to it when compiling fails).
        block: particles per block (:func:`~torchmocap.likelihoods.base.blockwise`): larger
            batches are evaluated block by block, their temporaries cache-sized (3x faster at
            4000 particles); a batch of at most ``block`` particles is one call, as before.
            None: always one call.

    ``requires = ("silhouettes",)``; ``prepare(frame)`` samples the foreground once per frame
    (views flagged in ``frame.view_dropped`` and empty masks are excluded).
    """

    requires = ("silhouettes",)

    differentiable_hint = ("the smooth silhouette term (smooth: true, e.g. "
                           "likelihood=smooth_image); the 0/1 coverage test has no gradient")

    @property
    def differentiable(self) -> bool:
        """The smooth variant only (the hard one's coverage test is 0/1)."""
        return self.smooth

    def __init__(self, body, rig, smooth: bool = False, fg_samples: int = 64,
                 blur: float | None = None, axis_samples: int = 5, across_samples: int = 3,
                 tau: float = 1.5, distance: float | None = None,
                 reference_width: float | None = None, compile: bool = False,
                 block: int | None = 512):
        super().__init__()
        if not isinstance(compile, bool):
            raise ValueError(f"compile: expected true or false, got {compile!r}")
        self._energy = CompiledFunction(silhouette_energy, "terms.silhouette.compile", compile)
        self.block = check_block(block)
        if reference_width is not None and (
                isinstance(reference_width, bool) or not isinstance(reference_width, (int, float))
                or not math.isfinite(reference_width) or reference_width <= 0):
            raise ValueError(f"reference_width: expected a finite image width in pixels > 0 or "
                             f"None, got {reference_width!r}")
        self.reference_width = None if reference_width is None else float(reference_width)
        # the views' widths as numbers, for the blur kernels (no host copy per frame)
        self._widths = [float(w) for w in rig.image_size[:, 0].tolist()]
        if distance is not None:
            if isinstance(distance, bool) or not isinstance(distance, (int, float)) \
                    or not math.isfinite(distance) or distance <= 0:
                raise ValueError(f"distance: expected a finite number of pixels > 0 or None, "
                                 f"got {distance!r}")
            if not smooth:
                raise ValueError("distance: the distance version is a differentiable term; "
                                 "set smooth: true with it")
            distance = float(distance)
        self.distance = distance
        if not isinstance(fg_samples, int) or isinstance(fg_samples, bool) or fg_samples < 1:
            raise ValueError(f"fg_samples: expected an int >= 1, got {fg_samples!r}")
        if axis_samples < 1 or across_samples < 1:
            raise ValueError("axis_samples, across_samples: expected ints >= 1")
        if not tau > 0:
            raise ValueError(f"tau: expected a value > 0, got {tau!r}")
        self.body = body
        self.rig = rig
        self.smooth = bool(smooth)
        self.fg_samples = fg_samples
        self.blur = (1.5 if self.smooth else 0.0) if blur is None else float(blur)
        if self.blur < 0:
            raise ValueError(f"blur: expected a value >= 0, got {blur!r}")
        self.axis_samples = int(axis_samples)
        self.across_samples = int(across_samples)
        self.tau = float(tau)

    def view_scale(self) -> torch.Tensor | float:
        """Per-view factor ``(C,)`` of the pixel settings (1.0 without ``reference_width``)."""
        if self.reference_width is None:
            return 1.0
        return self.rig.image_size[:, 0].to(self.body.radii.dtype) / self.reference_width

    def prepare(self, frame) -> SilhouetteObservation:
        view_valid = None
        if getattr(frame, "view_dropped", None) is not None:
            view_valid = ~frame.view_dropped.bool()
        if self.distance or self.reference_width is None:
            blur = 0.0 if self.distance else self.blur
        else:
            blur = [self.blur * w / self.reference_width for w in self._widths]
        return prepare_silhouettes(frame.silhouettes, self.fg_samples, blur=blur,
                                   view_valid=view_valid, dtype=self.body.radii.dtype,
                                   distance=self.distance is not None)

    def evidence(self, observation: SilhouetteObservation) -> bool:
        return bool(observation.view_valid.any())

    def energy(self, poses, observation: SilhouetteObservation) -> torch.Tensor:
        k = self.view_scale()
        return blockwise(self._energy, poses.endpoints(self.body), self.block, self.body.radii,
                         self.rig, observation, self.smooth, self.axis_samples,
                         self.across_samples, self.tau * k,
                         None if self.distance is None else self.distance * k,
                         self.rig.has_distortion)

    def extra_repr(self) -> str:
        ref = "" if self.reference_width is None else f", reference_width={self.reference_width:g}"
        ref += ", compile=True" if self._energy.enabled else ""
        if self.distance is not None:
            return f"distance={self.distance}, fg_samples={self.fg_samples}{ref}"
        return f"smooth={self.smooth}, fg_samples={self.fg_samples}, blur={self.blur}{ref}"


def render_capsule_silhouettes(body, rig, theta: torch.Tensor, chunk: int = 20000
                               ) -> torch.Tensor:
    """Exact capsule-model silhouettes ``(C, H, W)`` bool of one pose ``theta (D,)``.

    Every pixel centre inside the bounding box of a view's projected capsules is tested against
    every capsule (the same stadium model the likelihood uses), in chunks of pixels; a pixel
    outside that box is farther than every capsule's radius from its axis, so it is False
    without a test. Used for overlays, IoU reports and test oracles. ``(H, W)`` is the largest
    camera's image size; a smaller view fills the top-left corner (False beyond it), the layout
    of a sequence's silhouettes.
    """
    st = _stadiums(body.endpoints(body.skeleton(theta[None])), body.radii, rig)
    sizes = rig.image_size.long().cpu()
    W, H = int(sizes[:, 0].max()), int(sizes[:, 1].max())
    out = torch.zeros(sizes.shape[0], H, W, dtype=torch.bool)
    boxes = _stadium_boxes(st).cpu().tolist()  # (C, 4)
    for c, ((w, h), (x0, y0, x1, y1)) in enumerate(zip(sizes.tolist(), boxes)):
        if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
            continue  # no capsule in front of this camera
        x0, y0 = max(0, math.floor(x0)), max(0, math.floor(y0))
        x1, y1 = min(w, math.ceil(x1) + 1), min(h, math.ceil(y1) + 1)
        if x0 >= x1 or y0 >= y1:
            continue
        ys, xs = torch.meshgrid(torch.arange(y0, y1, device=st.ax.device),
                                torch.arange(x0, x1, device=st.ax.device), indexing="ij")
        q = torch.stack([xs, ys], -1).reshape(1, -1, 2).to(st.ax.dtype)  # pixel centres
        view = _Stadiums(*(f[c:c + 1] for f in st))
        inside = torch.empty(q.shape[1], dtype=torch.bool)
        for a in range(0, q.shape[1], chunk):
            margin = _coverage_margin(q[:, a:a + chunk], view, smooth=False)
            inside[a:a + chunk] = (margin[0, :, 0] > 0).cpu()
        out[c, y0:y1, x0:x1] = inside.view(y1 - y0, x1 - x0)
    return out


def _stadium_boxes(st: _Stadiums) -> torch.Tensor:
    """Per view the bounding box ``(C, 4)`` (x0, y0, x1, y1, pixels) of every stadium with a
    positive radius (each stadium lies within the box of its two end discs); infinite where a
    view has none."""
    r = torch.maximum(st.r0, st.r1)
    has = r > 0
    bx, by = st.ax + st.dx, st.ay + st.dy
    inf = torch.full((), float("inf"), dtype=st.ax.dtype, device=st.ax.device)
    lo_x = torch.where(has, torch.minimum(st.ax, bx) - r, inf).flatten(1).amin(1)
    lo_y = torch.where(has, torch.minimum(st.ay, by) - r, inf).flatten(1).amin(1)
    hi_x = torch.where(has, torch.maximum(st.ax, bx) + r, -inf).flatten(1).amax(1)
    hi_y = torch.where(has, torch.maximum(st.ay, by) + r, -inf).flatten(1).amax(1)
    return torch.stack([lo_x, lo_y, hi_x, hi_y], 1)


def soft_capsule_silhouettes(endpoints: torch.Tensor, radii: torch.Tensor, rig,
                             stride: int = 1, tau: float = 1.0) -> torch.Tensor:
    """Differentiable capsule silhouettes ``(P, C, H', W')`` in [0, 1] of capsule axes
    ``endpoints (P, B, 2, 3)`` with ``radii (B,)``: the sigmoid of each pixel centre's coverage
    margin ``r(t) − d`` (pixels, :func:`_coverage_margin`) over ``tau``, on every ``stride``-th
    pixel (``H' = ceil(H / stride)``) of the largest view's size ``(W, H)``; a smaller view
    fills the top-left corner (as in a sequence's masks) and is 0 outside its own image.
    Gradients reach the poses and the radii.

    Example:
        >>> from torchmocap.body import CapsuleBody
        >>> from torchmocap.cameras import make_ring_rig
        >>> from torchmocap.skeleton import human31
        >>> sk = human31(); body = CapsuleBody(sk).float()
        >>> ends = body.endpoints(sk(sk.zero_pose((2,))))
        >>> soft_capsule_silhouettes(ends, body.radii, make_ring_rig(4), stride=4).shape
        torch.Size([2, 4, 60, 80])
    """
    if endpoints.dim() != 4 or endpoints.shape[-2:] != (2, 3):
        raise ValueError(f"endpoints: expected shape (P, B, 2, 3), got {tuple(endpoints.shape)}")
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise ValueError(f"stride: expected an int >= 1, got {stride!r}")
    if not tau > 0:
        raise ValueError(f"tau: expected a value > 0, got {tau!r}")
    sizes = [tuple(int(v) for v in sz) for sz in rig.image_size.tolist()]
    W, H = max(w for w, _ in sizes), max(h for _, h in sizes)
    st = _stadiums(endpoints, radii, rig)
    dt = st.ax.dtype
    ys = torch.arange(0, H, stride, dtype=dt, device=st.ax.device)
    xs = torch.arange(0, W, stride, dtype=dt, device=st.ax.device)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    q = torch.stack([gx, gy], -1).reshape(1, -1, 2)
    C, P = st.ax.shape[0], endpoints.shape[0]
    margin = _coverage_margin(q.expand(C, -1, -1), st, smooth=True)  # (C, N, P)
    soft = torch.sigmoid(margin / tau)
    if len(set(sizes)) > 1:  # a smaller view: nothing outside its own image (the padding)
        own = torch.tensor(sizes, dtype=dt, device=st.ax.device)  # (C, 2)
        inside = (q[0, None, :, 0] < own[:, None, 0]) & (q[0, None, :, 1] < own[:, None, 1])
        soft = soft * inside[..., None].to(dt)
    return soft.permute(2, 0, 1).reshape(P, C, ys.numel(), xs.numel())


def check_fit_iou(iou: float, what: str, category: type[Warning] = UserWarning) -> None:
    """Warn (``category``) when a body fitted to masks overlaps them with an IoU below
    :data:`MIN_PLAUSIBLE_IOU`: inverted or all-foreground masks, or the calibration of other
    cameras (swapped), fit no body well, and the track would be reported as if nothing were
    wrong. ``what`` names the fit in the message."""
    import math
    import warnings

    if math.isfinite(iou) and iou < MIN_PLAUSIBLE_IOU:
        warnings.warn(f"{what}: the silhouette IoU of the fitted body is {iou:.2f}, far below a "
                      f"fit to a person's masks (0.5-0.8): masks inverted or all foreground, or "
                      "the calibration of other cameras?", category, stacklevel=3)


def silhouette_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-view intersection over union of boolean masks ``(C, H, W)``: ``(C,)``."""
    a, b = a.bool(), b.bool()
    inter = (a & b).flatten(1).sum(-1).double()
    union = (a | b).flatten(1).sum(-1).double()
    return inter / union.clamp_min(1)
