"""Capsule body: one capsule per skeleton bone; skin distances, surface samples, meshes.

A *bone* runs from a joint to each of its children and is named by the child joint (the same key
as :meth:`Skeleton.bone_lengths`). The skin is the union of the capsules. This is the body model
of Hauberg & Pedersen's point-cloud likelihood (eq. 15): ``D(θ, z)`` is the distance from an
observed point ``z`` to the skin, optionally restricted to the half of each capsule facing the
camera.

Shapes: ``B`` bones, ``N`` query points, ``*`` leading batch dims (e.g. particles ``P``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

__all__ = [
    "ANTHROPOMETRIC_RADIUS_RATIOS",
    "CapsuleBody",
    "anthropometric_radii",
    "capsule_distance",
    "capsule_endpoints",
    "capsules_to_trimesh",
    "export_mesh",
    "facing_camera",
    "rays_blocked_by_capsules",
    "sample_capsule_surface",
    "segment_closest_points",
    "segment_distance",
]

_EPS = 1e-12

#: Capsule radius as a fraction of stature, by body segment. Derived from mean circumferences
#: (radius = circumference / 2π, at mid-segment) of the 2012 U.S. Army anthropometric survey
#: (ANSUR II; Gordon et al., "2012 Anthropometric Survey of U.S. Army Personnel", Natick/TR-15/007,
#: 2014; male means, stature 1756 mm): head circ. ≈ 570 mm, neck ≈ 400, chest ≈ 1060 (treated
#: as a rounder torso of depth ≈ 2·0.13 m), waist/buttock ≈ 940–1040, mid-thigh ≈ 540, calf ≈ 390
#: averaged with ankle ≈ 230, upper arm ≈ 320, forearm ≈ 290 averaged with wrist ≈ 175, hand
#: thickness/breadth, foot height/breadth. Segment lengths follow Winter's proportions (Winter,
#: "Biomechanics and Motor Control of Human Movement", 4th ed., Wiley 2009, Fig. 4.1: thigh
#: 0.245 H, shank 0.246 H, upper arm 0.186 H, forearm 0.146 H), so a skeleton scaled to stature H
#: gets radii in proportion. Capsules are rotationally symmetric; the torso's elliptic section
#: is approximated by its mean radius.
ANTHROPOMETRIC_RADIUS_RATIOS: dict[str, float] = {
    "head": 0.052,
    "neck": 0.033,
    "chest": 0.075,
    "abdomen": 0.080,
    "pelvis_side": 0.055,
    "clavicle": 0.035,
    "upper_arm": 0.027,
    "forearm": 0.022,
    "hand": 0.019,
    "thigh": 0.048,
    "shank": 0.031,
    "foot": 0.025,
}

# child-joint name pattern -> segment; first match wins
_SEGMENT_PATTERNS: list[tuple[str, str]] = [
    (r"head_?top|head_?end|headend|top", "head"),
    (r"toe|foot_?end", "foot"),
    (r"ankle|foot", "shank"),
    (r"knee|leg(?!.*up)|shin", "thigh"),
    (r"hip|upleg|thigh", "pelvis_side"),
    (r"hand|finger|fingertip", "hand"),
    (r"wrist", "forearm"),
    (r"elbow|forearm", "upper_arm"),
    (r"shoulder|arm|scapula", "clavicle"),
    (r"head", "neck"),
    (r"neck|thorax|chest|clavicle", "chest"),
    (r"spine|back|abdomen|belly|torso|lumbar", "abdomen"),
]


def _segment_of(bone: str) -> str | None:
    name = bone.lower()
    for pat, seg in _SEGMENT_PATTERNS:
        if re.search(pat, name):
            return seg
    return None


def anthropometric_radii(bone_names: list[str], bone_lengths: Tensor, height: float,
                         overrides: Mapping[str, float] | None = None,
                         default_length_ratio: float = 0.15) -> Tensor:
    """Per-bone capsule radii from :data:`ANTHROPOMETRIC_RADIUS_RATIOS`.

    Args:
        bone_names: ``B`` bone names (child joint names), matched by pattern to a body segment
            (``l_knee`` → thigh, ``l_ankle`` → shank, ``l_elbow`` → upper arm, ...).
        bone_lengths: ``(B,)`` rest bone lengths (metres); unmatched bones get
            ``default_length_ratio × length``.
        height: stature in metres.
        overrides: ``{bone_name: radius_m}`` taking precedence.

    Returns:
        ``(B,)`` radii in metres (float64).
    """
    if not (math.isfinite(height) and height > 0):
        raise ValueError(f"height: expected a positive number of metres, got {height}")
    overrides = dict(overrides or {})
    unknown = set(overrides) - set(bone_names)
    if unknown:
        raise ValueError(f"radii: unknown bone name(s) {sorted(unknown)}; bones are {bone_names}")
    out = []
    for i, b in enumerate(bone_names):
        if b in overrides:
            r = float(overrides[b])
            if not (math.isfinite(r) and r > 0):
                raise ValueError(f"radii[{b!r}]: expected a positive radius, got {r}")
        else:
            seg = _segment_of(b)
            r = ANTHROPOMETRIC_RADIUS_RATIOS[seg] * height if seg else \
                default_length_ratio * float(bone_lengths[i])
        out.append(r)
    return torch.tensor(out, dtype=torch.float64)


def _positions(kin: Any) -> Tensor:
    return kin.positions if hasattr(kin, "positions") else kin


def capsule_endpoints(positions: Tensor, parent_index: Tensor, child_index: Tensor,
                      end_shrink: Tensor | None = None, rotations: Tensor | None = None,
                      axis_offsets: Tensor | None = None) -> Tensor:
    """Bone segments ``(*, B, 2, 3)`` (start = parent joint, end = child joint) from ``(*, J, 3)``.

    ``end_shrink (B,)`` pulls each segment's end back towards its start by that many metres
    (at most the bone length): with the capsule radius for bones ending at an end site (head top,
    toe, hand tip) the skin then ends at the end site instead of a radius beyond it.
    ``axis_offsets (B, 3)`` moves each whole segment by that vector in its parent joint's frame
    (``rotations (*, J, 3, 3)``, the joints' global orientations): a capsule whose flesh does not
    sit on the bone, e.g. a head whose centre lies in front of the neck's axis.
    """
    if positions.dim() < 2 or positions.shape[-1] != 3:
        raise ValueError(f"positions: expected shape (*, J, 3), got {tuple(positions.shape)}")
    a = positions[..., parent_index, :]
    b = positions[..., child_index, :]
    if end_shrink is not None:
        ab = b - a
        L = _safe_norm(ab)
        k = torch.minimum(end_shrink.to(ab.dtype), L) / L
        b = b - k[..., None] * ab
    if axis_offsets is not None:
        if rotations is None or rotations.shape[-2:] != (3, 3) or \
                rotations.shape[:-2] != positions.shape[:-1]:
            raise ValueError("rotations: capsule axis offsets need the joints' global rotations "
                             f"(*, J, 3, 3) beside positions {tuple(positions.shape)}, got "
                             f"{None if rotations is None else tuple(rotations.shape)}")
        off = (rotations[..., parent_index, :, :] @ axis_offsets.to(a)[:, :, None])[..., 0]
        a, b = a + off, b + off
    return torch.stack([a, b], -2)


def segment_closest_points(points: Tensor, endpoints: Tensor) -> tuple[Tensor, Tensor]:
    """Closest points on every segment to every point.

    Args:
        points: ``(*, N, 3)``.
        endpoints: ``(*, B, 2, 3)``.

    Returns:
        ``closest (*, N, B, 3)`` and the segment parameter ``s (*, N, B)`` in ``[0, 1]``.
    """
    a = endpoints[..., None, :, 0, :]  # (*, 1, B, 3)
    ab = endpoints[..., None, :, 1, :] - a
    ap = points[..., :, None, :] - a  # (*, N, B, 3)
    denom = (ab * ab).sum(-1).clamp_min(_EPS)
    s = ((ap * ab).sum(-1) / denom).clamp(0.0, 1.0)
    return a + s[..., None] * ab, s


def _safe_norm(x: Tensor) -> Tensor:
    return (x * x).sum(-1).clamp_min(_EPS).sqrt()


def segment_distance(points: Tensor, endpoints: Tensor) -> Tensor:
    """Distance ``(*, N, B)`` from points ``(*, N, 3)`` to segments ``(*, B, 2, 3)``.

    Expanded into dot products (two batched matmuls, no ``(*, N, B, 3)`` intermediate), with
    coordinates centred on the segments' mean to limit cancellation: ~4× faster and ~3× less
    memory than :func:`segment_closest_points` for particle batches. The distance is clamped at
    1e-6 m from below (the gradient of ``‖·‖`` is undefined on the axis itself).
    """
    centre = endpoints.mean(dim=(-3, -2), keepdim=True)[..., 0, :]  # (*, 1, 3)
    a = endpoints[..., 0, :] - centre  # (*, B, 3)
    ab = endpoints[..., 1, :] - endpoints[..., 0, :]
    p = points - centre  # (*, N, 3)
    ab2 = (ab * ab).sum(-1).clamp_min(_EPS)  # (*, B)
    a_ab = (a * ab).sum(-1)
    p_ab = p @ ab.transpose(-1, -2)  # (*, N, B)
    p_a = p @ a.transpose(-1, -2)
    s = ((p_ab - a_ab[..., None, :]) / ab2[..., None, :]).clamp(0.0, 1.0)
    pp = (p * p).sum(-1, keepdim=True)  # (*, N, 1)
    aa = (a * a).sum(-1)[..., None, :]  # (*, 1, B)
    d2 = pp - 2 * p_a + aa - 2 * s * (p_ab - a_ab[..., None, :]) + s * s * ab2[..., None, :]
    return d2.clamp_min(1e-12).sqrt()


def rays_blocked_by_capsules(origins: Tensor, points: Tensor, endpoints: Tensor, radii: Tensor,
                             own: Tensor | None = None, stop: float = 0.005,
                             ignore: Tensor | None = None) -> Tensor:
    """Whether the line of sight from each origin to each point passes through a capsule.

    The ray segment runs from ``origins (C, 3)`` (camera centres) to ``stop`` metres before each
    point of ``points (P, N, 3)``; it is blocked when it comes closer than ``radii (B,)`` to the
    axis of one of the capsules ``endpoints (P, B, 2, 3)`` (the closest points of two segments,
    Ericson, *Real-Time Collision Detection* §5.1.9), skipping each point's own capsule
    ``own (N,)`` (a point on a capsule's camera-facing skin is never hidden by that capsule),
    and every capsule flagged in ``ignore`` (``(N, B)`` or ``(P, N, B)`` bool: e.g. the capsules
    a joint sits inside). Returns ``(C, P, N)`` bool. Memory and time are ``O(C P N B)``; no
    gradient.
    """
    if origins.dim() != 2 or origins.shape[-1] != 3:
        raise ValueError(f"origins: expected shape (C, 3), got {tuple(origins.shape)}")
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"points: expected shape (P, N, 3), got {tuple(points.shape)}")
    if endpoints.dim() != 4 or endpoints.shape[-2:] != (2, 3) \
            or endpoints.shape[0] != points.shape[0]:
        raise ValueError(f"endpoints: expected shape ({points.shape[0]}, B, 2, 3), got "
                         f"{tuple(endpoints.shape)}")
    if radii.shape != endpoints.shape[1:2]:
        raise ValueError(f"radii: expected shape ({endpoints.shape[1]},), got "
                         f"{tuple(radii.shape)}")
    if own is not None and own.shape != points.shape[1:2]:
        raise ValueError(f"own: expected shape ({points.shape[1]},) capsule indices, got "
                         f"{tuple(own.shape)}")
    B = endpoints.shape[1]
    if ignore is not None and (ignore.dtype != torch.bool or ignore.shape not in (
            (points.shape[1], B), (points.shape[0], points.shape[1], B))):
        raise ValueError(f"ignore: expected a bool tensor of shape ({points.shape[1]}, {B}) or "
                         f"({points.shape[0]}, {points.shape[1]}, {B}), got "
                         f"{tuple(ignore.shape)} {ignore.dtype}")
    with torch.no_grad():
        dt = points.dtype
        endpoints = endpoints.to(dt)
        o = origins.to(dt)[:, None, None, :]  # (C, 1, 1, 3)
        d1 = points[None] - o  # (C, P, N, 3)
        n1 = d1.norm(dim=-1, keepdim=True).clamp_min(_EPS)
        d1 = d1 * (1 - stop / n1).clamp_min(0)
        p2 = endpoints[:, :, 0]  # (P, B, 3)
        d2 = endpoints[:, :, 1] - p2
        r = o - p2[None]  # (C, P, B, 3): origin - capsule start
        a = (d1 * d1).sum(-1)[..., None]  # (C, P, N, 1)
        e = (d2 * d2).sum(-1).clamp_min(_EPS)[None, :, None]  # (1, P, 1, B)
        b = torch.einsum("cpnk,pbk->cpnb", d1, d2)
        c = torch.einsum("cpnk,cpbk->cpnb", d1, r)
        f = (d2[None] * r).sum(-1)[:, :, None]  # (C, P, 1, B)
        rr = (r * r).sum(-1)[:, :, None]
        denom = a * e - b * b
        s = torch.where(denom > 1e-12, ((b * f - c * e) / denom.clamp_min(1e-12)).clamp(0, 1),
                        torch.zeros_like(b))
        t = (b * s + f) / e
        a_ = a.clamp_min(_EPS)
        s = torch.where(t < 0, (-c / a_).clamp(0, 1), torch.where(t > 1, ((b - c) / a_)
                                                                    .clamp(0, 1), s))
        t = t.clamp(0, 1)
        d2min = rr + s * s * a + t * t * e + 2 * s * c - 2 * t * f - 2 * s * t * b
        hit = d2min < radii.to(dt).square()  # (C, P, N, B)
        if own is not None:
            hit = hit & (own.to(hit.device)[:, None] != torch.arange(
                endpoints.shape[1], device=hit.device))
        if ignore is not None:
            hit = hit & ~ignore.to(hit.device)
        return hit.any(-1)


def _facing_half_distance(points: Tensor, endpoints: Tensor, r: Tensor, c: Tensor) -> Tensor:
    """``(*, N, B)`` distance of every point to the camera-facing half of every capsule.

    For the closest axis point ``s = a + t â`` (``t`` clamped to ``[0, L]``) and ``d = z − s``:
    the nearest skin point faces the camera iff ``(c − s)·d ≥ r ‖d‖`` (then the distance is
    ``|‖d‖ − r|``); otherwise it is the nearer rim point ``s ± r w``, ``w = â × (c − s) / ‖·‖``,
    at ``sqrt(‖d‖² − 2 r |d·w| + r²)``. Since ``â × (c − s) = â × (c − a) =: q`` does not depend
    on ``t`` and ``â·q = 0``, ``d·w = (z − a)·q / ‖q‖``; every term is a dot product of the
    point with a per-capsule vector (``a``, ``â``, ``q``: one batched matmul) or a per-capsule
    scalar, so no ``(*, N, B, 3)`` intermediate is formed. Coordinates are centred on the
    capsules' mean against cancellation. ``r (*, 1, B)``, ``c (*, 3)``.
    """
    B = endpoints.shape[-3]
    centre = endpoints.mean(dim=(-3, -2))  # (*, 3)
    a = endpoints[..., 0, :] - centre[..., None, :]  # (*, B, 3)
    ab = endpoints[..., 1, :] - endpoints[..., 0, :]
    length = _safe_norm(ab)  # (*, B)
    ax = ab / length[..., None]
    z = points - centre[..., None, :]  # (*, N, 3)
    cc = c - centre  # (*, 3)
    q = torch.linalg.cross(ax, cc[..., None, :] - a)  # (*, B, 3)
    qn = (q * q).sum(-1).sqrt()
    degenerate = qn <= 1e-9  # camera on the axis line: w = the normal, so d.w = |d|
    q = q / torch.where(degenerate, 1.0, qn)[..., None]
    za, zu, zq = (z @ torch.cat([a, ax, q], -2).transpose(-1, -2)).split(B, -1)  # (*, N, B)
    aa, au, aq = (a * a).sum(-1), (a * ax).sum(-1), (a * q).sum(-1)  # (*, B)
    ac = (a * cc[..., None, :]).sum(-1)
    cu = (cc[..., None, :] * ax).sum(-1) - au  # (c - a).â
    zz = (z * z).sum(-1, keepdim=True)  # (*, N, 1)
    zc = (z * cc[..., None, :]).sum(-1, keepdim=True)
    u = zu - au[..., None, :]  # (z - a).â
    t = torch.minimum(u.clamp_min(0.0), length[..., None, :])
    zma = zz - 2 * za + aa[..., None, :]  # |z - a|^2
    tt = t * (t - 2 * u)
    d2 = (zma + tt).clamp_min(_EPS)  # |d|^2
    dist = d2.sqrt()
    # (c - s).d = (c - a).(z - a) - t (c - a).â - t u + t^2
    toward = zc - ac[..., None, :] - za + aa[..., None, :] - t * cu[..., None, :] + tt + t * u
    facing = toward >= r * dist
    dw = torch.where(degenerate[..., None, :], dist, (zq - aq[..., None, :]).abs())
    rim = (d2 - 2 * r * dw + r * r).clamp_min(_EPS).sqrt()
    return torch.where(facing, (dist - r).abs(), rim)


def capsule_distance(points: Tensor, endpoints: Tensor, radii: Tensor,
                     camera_center: Tensor | None = None, reduce: bool = True) -> Tensor:
    """Distance from points to a union of capsules (the skin).

    Without ``camera_center`` this is the signed distance ``min_b (‖z − seg_b‖ − r_b)``
    (negative inside). With ``camera_center`` it is the unsigned distance to the *camera-facing
    half* of each capsule (Hauberg & Pedersen eq. 15): if the nearest surface point faces the
    camera the distance is ``|‖z − s‖ − r|``, otherwise it is the distance to the capsule's rim
    (the silhouette circle ``s ± r w``, ``w ⟂`` axis and view direction), then min over capsules.

    Args:
        points: ``(*, N, 3)`` query points.
        endpoints: ``(*, B, 2, 3)`` capsule axes.
        radii: ``(B,)`` or ``(*, B)`` radii.
        camera_center: optional ``(*, 3)`` camera centre.
        reduce: return the min over capsules ``(*, N)``; else per capsule ``(*, N, B)``.

    Returns:
        ``(*, N)`` (or ``(*, N, B)``) distances in metres. Differentiable (use float64 for
        gradcheck); ties in the min get the gradient of one capsule.

    Example:
        >>> e = torch.tensor([[[0., 0, 0], [0, 0, 1]]])
        >>> capsule_distance(torch.tensor([[1., 0, 0.5]]), e, torch.tensor([0.1]))
        tensor([0.9000])
    """
    if points.dim() < 2 or points.shape[-1] != 3:
        raise ValueError(f"points: expected shape (*, N, 3), got {tuple(points.shape)}")
    if endpoints.dim() < 3 or endpoints.shape[-2:] != (2, 3):
        raise ValueError(f"endpoints: expected shape (*, B, 2, 3), got {tuple(endpoints.shape)}")
    if radii.shape[-1] != endpoints.shape[-3]:
        raise ValueError(f"radii: expected {endpoints.shape[-3]} radii (one per capsule), got "
                         f"shape {tuple(radii.shape)}")
    r = radii.to(points.dtype)[..., None, :]  # (*, 1, B)
    if camera_center is None:
        signed = segment_distance(points, endpoints) - r
        return signed.min(-1).values if reduce else signed
    front = _facing_half_distance(points, endpoints, r, camera_center.to(points.dtype))
    return front.min(-1).values if reduce else front


def facing_camera(points: Tensor, normals: Tensor, camera_centers: Tensor) -> Tensor:
    """Whether surface points face the camera(s): ``(c − p) · n > 0``.

    Args:
        points: ``(*, N, 3)`` surface points; normals ``(*, N, 3)`` outward unit normals.
        camera_centers: ``(C, 3)`` camera centres (e.g. ``rig.camera_centers()``).

    Returns:
        ``(*, C, N)`` bool. (Self-occlusion by other body parts is not tested.)
    """
    c = camera_centers.to(points.dtype)[:, None, :]  # (C, 1, 3)
    return ((c - points[..., None, :, :]) * normals[..., None, :, :]).sum(-1) > 0


def _orthonormal_frame(axis: Tensor) -> tuple[Tensor, Tensor]:
    helper = torch.zeros_like(axis)
    use_x = axis[..., 0].abs() < 0.9
    helper[..., 0] = use_x.to(axis.dtype)
    helper[..., 1] = (~use_x).to(axis.dtype)
    u = torch.linalg.cross(axis, helper)
    u = u / _safe_norm(u)[..., None]
    v = torch.linalg.cross(axis, u)
    return u, v


def sample_capsule_surface(endpoints: Tensor, radii: Tensor, n: int,
                           generator: torch.Generator | None = None
                           ) -> tuple[Tensor, Tensor, Tensor]:
    """Uniform (area-weighted) random points on the union of capsule surfaces.

    Each capsule's surface (cylinder ``2πrL`` + two hemispheres ``4πr²``) is sampled uniformly;
    capsules are chosen in proportion to their area (points inside overlapping capsules are kept).

    Args:
        endpoints: ``(*, B, 2, 3)``; radii ``(B,)``.
        n: points per body.
        generator: the source of randomness.

    Returns:
        ``points (*, n, 3)``, outward unit ``normals (*, n, 3)``, ``bone (*, n)`` indices.
    """
    if n < 1:
        raise ValueError(f"n: expected a positive number of points, got {n}")
    batch = endpoints.shape[:-3]
    B = endpoints.shape[-3]
    dtype, device = endpoints.dtype, endpoints.device
    ep = endpoints.reshape(-1, B, 2, 3)
    M = ep.shape[0]
    r = radii.to(dtype).expand(B)
    a, b = ep[..., 0, :], ep[..., 1, :]
    length = _safe_norm(b - a)  # (M, B)
    cyl = 2 * math.pi * r * length
    sph = (4 * math.pi * r * r).expand_as(cyl)
    # random numbers are drawn on the generator's device, then moved to the data's
    gdev = generator.device if generator is not None else device
    probs = (cyl + sph).detach().to(gdev)
    bone = torch.multinomial(probs, n, replacement=True, generator=generator).to(device)
    u01 = torch.rand(M, n, 3, generator=generator, dtype=dtype, device=gdev).to(device)
    g = torch.randn(M, n, 3, generator=generator, dtype=dtype, device=gdev).to(device)
    gather = lambda x: torch.gather(x, 1, bone.unsqueeze(-1).expand(M, n, x.shape[-1])) \
        if x.dim() == 3 else torch.gather(x, 1, bone)
    a_s, b_s = gather(a), gather(b)
    L_s, r_s = gather(length), r[bone]
    cyl_s, sph_s = gather(cyl), gather(sph)
    axis = (b_s - a_s) / L_s[..., None]
    e1, e2 = _orthonormal_frame(axis)
    on_cyl = u01[..., 0] * (cyl_s + sph_s) < cyl_s
    phi = 2 * math.pi * u01[..., 1]
    radial = torch.cos(phi)[..., None] * e1 + torch.sin(phi)[..., None] * e2
    p_cyl = a_s + u01[..., 2, None] * (b_s - a_s) + r_s[..., None] * radial
    d = g / _safe_norm(g)[..., None]
    centre = torch.where(((d * axis).sum(-1) >= 0)[..., None], b_s, a_s)
    p_sph = centre + r_s[..., None] * d
    points = torch.where(on_cyl[..., None], p_cyl, p_sph)
    normals = torch.where(on_cyl[..., None], radial, d)
    return (points.reshape(*batch, n, 3), normals.reshape(*batch, n, 3),
            bone.reshape(*batch, n))


def capsules_to_trimesh(endpoints: Tensor, radii: Tensor, sections: int = 16):
    """A ``trimesh.Trimesh`` of one pose's capsules ``(B, 2, 3)`` (concatenated, not unioned)."""
    import numpy as np
    import trimesh

    if endpoints.dim() != 3 or endpoints.shape[-2:] != (2, 3):
        raise ValueError(f"endpoints: expected one pose (B, 2, 3), got {tuple(endpoints.shape)}")
    meshes = []
    ep = endpoints.detach().cpu().double().numpy()
    rr = radii.detach().cpu().double().expand(ep.shape[0]).numpy()
    for (a, b), r in zip(ep, rr):
        L = float(np.linalg.norm(b - a))
        m = trimesh.creation.capsule(height=max(L, 1e-9), radius=float(r),
                                     count=[sections, sections])
        z = (b - a) / L if L > 1e-9 else np.array([0.0, 0.0, 1.0])
        T = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], z)
        T[:3, 3] = (a + b) / 2
        m.apply_transform(T)
        meshes.append(m)
    return trimesh.util.concatenate(meshes)


def export_mesh(mesh, path: str | Path) -> Path:
    """Export a trimesh to ``.obj``, ``.glb``, ``.ply`` or ``.stl`` (by extension)."""
    path = Path(path)
    if path.suffix.lower() not in (".obj", ".glb", ".gltf", ".ply", ".stl"):
        raise ValueError(f"path: unsupported mesh format {path.suffix!r}; use .obj/.glb/.ply/.stl")
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(path)
    return path


class CapsuleBody(nn.Module):
    """Union-of-capsules skin for any :class:`~torchmocap.skeleton.Skeleton`.

    One capsule per bone (from a joint to each child joint, named by the child). Radii come from
    :func:`anthropometric_radii` for the skeleton's stature (vertical extent of its rest joints,
    or ``height``), overridable per bone.

    Args:
        skeleton: the skeleton (its rest pose defines the bones and stature).
        radii: ``{bone_name: radius_m}`` overrides (bone name = child joint name).
        height: stature in metres (default: rest joints' z-extent).
        shorten_end_sites: pull the end of bones that end at an end site (a joint without
            children) back by the radius, so the skin ends there (default True).
        axis_offsets: ``{bone_name: (x, y, z)}`` metres: the capsule moved off its bone by this
            vector in the parent joint's frame (default: every capsule on its bone). Fitted to a
            subject by :class:`~torchmocap.filters.SilhouetteBodyFit` (``offsets``).

    Example:
        >>> from torchmocap.skeleton import human31
        >>> body = CapsuleBody(human31())
        >>> kin = body.skeleton(body.skeleton.zero_pose((5,)))
        >>> body.skin_distance(torch.zeros(5, 7, 3), kin).shape
        torch.Size([5, 7])
    """

    parent_index: Tensor
    child_index: Tensor
    radii: Tensor
    end_shrink: Tensor
    axis_offsets: Tensor

    def __init__(self, skeleton: nn.Module, radii: Mapping[str, float] | None = None,
                 height: float | None = None, shorten_end_sites: bool = True,
                 axis_offsets: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        self.skeleton = skeleton
        parents = list(skeleton.parents)
        names = list(skeleton.joint_names)
        child = [j for j in range(len(parents)) if parents[j] >= 0]
        if not child:
            raise ValueError("skeleton: needs at least one bone (a joint with a parent)")
        self.bone_names = [names[j] for j in child]
        rest = skeleton.joint_positions(skeleton.zero_pose(dtype=torch.float64))
        if height is None:
            height = float(rest[:, 2].max() - rest[:, 2].min())
        self.height = float(height)
        lengths = (rest[child] - rest[[parents[j] for j in child]]).norm(dim=-1)
        self.register_buffer("parent_index", torch.tensor([parents[j] for j in child]))
        self.register_buffer("child_index", torch.tensor(child))
        self.register_buffer("radii", anthropometric_radii(self.bone_names, lengths, self.height,
                                                           radii))
        leaf = torch.tensor([not any(p == j for p in parents) for j in child])
        shrink = torch.where(leaf, self.radii, torch.zeros_like(self.radii))
        self.register_buffer("end_shrink", shrink if shorten_end_sites else torch.zeros_like(
            self.radii))
        off = torch.zeros(len(child), 3, dtype=self.radii.dtype)
        for bone, v in (axis_offsets or {}).items():
            if bone not in self.bone_names:
                raise ValueError(f"axis_offsets: unknown bone {bone!r}; bones: {self.bone_names}")
            t = torch.as_tensor(v, dtype=off.dtype)
            if t.shape != (3,) or not bool(torch.isfinite(t).all()):
                raise ValueError(f"axis_offsets[{bone!r}]: expected 3 finite metres, got {v!r}")
            off[self.bone_names.index(bone)] = t
        self.register_buffer("axis_offsets", off)

    @property
    def has_axis_offsets(self) -> bool:
        """Whether any capsule is moved off its bone (``endpoints`` then needs rotations)."""
        return bool(self.axis_offsets.any())

    @property
    def num_bones(self) -> int:
        return len(self.bone_names)

    def radius(self, bone: str) -> float:
        return float(self.radii[self.bone_names.index(bone)])

    def endpoints(self, kin: Any) -> Tensor:
        """Capsule axes ``(*, B, 2, 3)`` from ``Kinematics`` (or positions ``(*, J, 3)`` when no
        capsule has an axis offset)."""
        if not self.has_axis_offsets:
            return capsule_endpoints(_positions(kin), self.parent_index, self.child_index,
                                     self.end_shrink)
        if not hasattr(kin, "rotations"):
            raise ValueError("kin: this body has capsule axis offsets, which need the joints' "
                             "rotations: pass Kinematics (skeleton(theta)), not positions")
        return capsule_endpoints(kin.positions, self.parent_index, self.child_index,
                                 self.end_shrink, kin.rotations, self.axis_offsets)

    def forward(self, theta: Tensor) -> Tensor:
        """Capsule axes ``(*, B, 2, 3)`` of poses ``theta (*, D)``."""
        return self.endpoints(self.skeleton(theta))

    def skin_distance(self, points: Tensor, kin: Any, camera_center: Tensor | None = None
                      ) -> Tensor:
        """Distance ``(*, N)`` of ``points (*, N, 3)`` to the skin; see :func:`capsule_distance`."""
        return capsule_distance(points, self.endpoints(kin), self.radii, camera_center)

    point_to_skin_distance = skin_distance

    def sample_surface_points(self, kin: Any, n: int, generator: torch.Generator | None = None
                              ) -> tuple[Tensor, Tensor, Tensor]:
        """``points (*, n, 3)``, ``normals``, ``bone`` indices on the skin of each pose."""
        return sample_capsule_surface(self.endpoints(kin), self.radii, n, generator)

    def to_trimesh(self, kin: Any, sections: int = 16):
        """A ``trimesh.Trimesh`` of a single pose (``Kinematics`` without batch dims)."""
        ep = self.endpoints(kin)
        if ep.dim() != 3:
            raise ValueError(f"kin: expected a single pose, got batch shape {tuple(ep.shape[:-3])}")
        return capsules_to_trimesh(ep, self.radii, sections)

    def export(self, kin: Any, path: str | Path) -> Path:
        """Write a single pose's capsules to ``.obj``/``.glb``/``.ply``/``.stl``."""
        return export_mesh(self.to_trimesh(kin), path)

    def extra_repr(self) -> str:
        out = f"num_bones={self.num_bones}, height={self.height:.3f}"
        if self.has_axis_offsets:
            moved = [b for b, o in zip(self.bone_names, self.axis_offsets) if bool(o.any())]
            out += f", axis_offsets={moved}"
        return out
