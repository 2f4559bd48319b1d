"""Vectorised triangle rasterisation in torch: filled masks and a z-buffer.

Pixel ``(x, y)`` covers ``[x - 0.5, x + 0.5) × [y - 0.5, y + 0.5)`` and is sampled at its centre
(the convention of :func:`~torchmocap.cameras.project_points`). Each triangle is filled by testing
the pixel centres of its bounding box with normalised edge functions (= screen-space barycentric
coordinates). The candidate pixels of all triangles of all images are enumerated at once as a
ragged expansion (``repeat_interleave`` of triangle ids by bounding-box area), so the cost is
proportional to the covered area, not to ``triangles × pixels``; images are processed in chunks
to bound memory. Triangles with a vertex behind the near plane are skipped; both windings are
filled (masks do not depend on the mesh's orientation).

The z-buffer keeps, per pixel, the nearest triangle: ``scatter_reduce(amin)`` of a packed
``(quantised depth, face id)`` key; depth and perspective-correct barycentrics of the winner are
then recomputed exactly, so a back-projected pixel lies on its triangle's plane.

Lens distortion moves vertices, not edges: triangles are drawn with straight edges between the
distorted vertex projections (exact for the distortion-free synthetic rigs, a small error for
small triangles otherwise).

Shapes: ``B`` images (frames × cameras flattened), ``V`` vertices, ``F`` faces, ``H × W`` image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "ZBuffer",
    "capsule_mesh",
    "face_normals",
    "rasterize_mask",
    "rasterize_zbuffer",
    "vertex_normals",
]

_NEAR = 1e-3
_FACE_BITS = 22  # face ids < 4M
_DEPTH_SCALE = 1e6  # quantised depth unit: 1 µm


@dataclass
class _Candidates:
    image: Tensor  # (N,) image index of each candidate pixel
    face: Tensor  # (N,) face index
    x: Tensor  # (N,) pixel column
    y: Tensor  # (N,) pixel row
    bary: Tensor  # (N, 3) screen-space barycentrics
    inv_z: Tensor  # (N, 3) inverse vertex depths (for perspective-correct depth)


def _check_inputs(pixels: Tensor, depth: Tensor, faces: Tensor) -> None:
    if pixels.dim() != 3 or pixels.shape[-1] != 2:
        raise ValueError(f"pixels: expected shape (B, V, 2), got {tuple(pixels.shape)}")
    if depth.shape != pixels.shape[:-1]:
        raise ValueError(f"depth: expected shape {tuple(pixels.shape[:-1])} (B, V), got "
                         f"{tuple(depth.shape)}")
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {tuple(faces.shape)}")


def _triangle_setup(pixels: Tensor, depth: Tensor, faces: Tensor, width: int, height: int):
    """Triangles whose bounding box holds pixel centres, with their edge-function coefficients.

    Returns ``ids (K,)`` flat (image · F + face) indices, candidate counts ``n (K,)``, box corners
    ``xmin, ymin``, box widths ``w`` and ``coef (K, 12)``: rows of the normalised edge functions
    ``λ_i(p) = A_i px + B_i py + C_i`` (``A``, ``B``, ``C``, 3 each) and the vertices' ``1/z``.
    Coefficients are only formed for the triangles that cover at least one pixel centre (most
    triangles of a dense mesh are smaller than a pixel).
    """
    tri = pixels[:, faces]  # (B, F, 3, 2)
    x, y = tri[..., 0], tri[..., 1]
    x_lo, x_hi = x.amin(-1), x.amax(-1)
    y_lo, y_hi = y.amin(-1), y.amax(-1)
    xmin = torch.ceil(x_lo).clamp(0, width - 1)
    xmax = torch.floor(x_hi).clamp(-1, width - 1)
    ymin = torch.ceil(y_lo).clamp(0, height - 1)
    ymax = torch.floor(y_hi).clamp(-1, height - 1)
    w = (xmax - xmin + 1).clamp_min(0)
    h = (ymax - ymin + 1).clamp_min(0)
    inside_img = (x_hi >= 0) & (x_lo <= width - 1) & (y_hi >= 0) & (y_lo <= height - 1)
    n = torch.where(inside_img, w * h, torch.zeros_like(w)).reshape(-1)
    ids = (n > 0).nonzero().squeeze(-1)
    F = faces.shape[0]
    t = tri.reshape(-1, 3, 2)[ids]  # (K, 3, 2)
    z = depth[torch.div(ids, F, rounding_mode="floor")[:, None], faces[ids % F]]  # (K, 3)
    (x0, y0), (x1, y1), (x2, y2) = t[:, 0].unbind(-1), t[:, 1].unbind(-1), t[:, 2].unbind(-1)
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)  # twice the signed area
    ok = (z > _NEAR).all(-1) & (area.abs() > 1e-12) & torch.isfinite(area)
    inv = 1.0 / torch.where(ok, area, torch.ones_like(area))
    coef = torch.stack([y1 - y2, y2 - y0, y0 - y1, x2 - x1, x0 - x2, x1 - x0,
                        x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0], -1) * inv[:, None]
    coef = torch.cat([coef, 1.0 / z.clamp_min(_NEAR)], -1)  # (K, 12)
    keep = ok.nonzero().squeeze(-1)
    ids = ids[keep]
    return (ids, n[ids].long(), xmin.reshape(-1)[ids].long(), ymin.reshape(-1)[ids].long(),
            w.reshape(-1)[ids].long(), coef[keep])


def _candidates(pixels: Tensor, depth: Tensor, faces: Tensor, width: int, height: int,
                eps: float) -> _Candidates:
    F = faces.shape[0]
    tids, n, xmin, ymin, w, coef = _triangle_setup(pixels, depth, faces, width, height)
    total = int(n.sum())
    dev = pixels.device
    local = torch.repeat_interleave(torch.arange(tids.shape[0], device=dev), n,
                                    output_size=total)
    start = torch.cumsum(n, 0) - n
    k = torch.arange(total, device=dev) - start[local]
    wi = w[local]
    px = xmin[local] + k % wi
    py = ymin[local] + torch.div(k, wi, rounding_mode="floor")
    c = coef[local]
    pxf, pyf = px.to(c.dtype), py.to(c.dtype)
    bary = c[:, 0:3] * pxf[:, None] + c[:, 3:6] * pyf[:, None] + c[:, 6:9]
    inside = (bary >= -eps).all(-1)
    ids = tids[local[inside]]
    return _Candidates(torch.div(ids, F, rounding_mode="floor"), ids % F, px[inside],
                       py[inside], bary[inside], c[inside, 9:12])


def _eps(x: Tensor) -> float:
    """Tolerance on barycentrics: pixel centres on a shared edge belong to both triangles."""
    return 1e-5 if x.dtype in (torch.float32, torch.float16, torch.bfloat16) else 1e-9


def _chunks(B: int, per_image: float, budget: int) -> list[tuple[int, int]]:
    step = max(1, int(budget // max(per_image, 1.0)))
    return [(s, min(B, s + step)) for s in range(0, B, step)]


def _estimate_candidates(pixels: Tensor, faces: Tensor, width: int, height: int) -> float:
    """Rough candidates per image from the first image's triangle bounding boxes."""
    tri = pixels[:1, faces]
    ext = (tri.amax(-2) - tri.amin(-2)).clamp(0, max(width, height)) + 1
    return float((ext[..., 0] * ext[..., 1]).sum()) + 1.0


def rasterize_mask(pixels: Tensor, depth: Tensor, faces: Tensor, width: int, height: int,
                   budget: int = 4_000_000) -> Tensor:
    """Filled binary masks of triangle meshes.

    Args:
        pixels: ``(B, V, 2)`` projected vertices (u, v) in pixels.
        depth: ``(B, V)`` camera depths of the vertices (triangles with a vertex closer than
            1 mm are skipped).
        faces: ``(F, 3)`` vertex indices.
        width, height: image size.
        budget: candidate pixels processed at once (memory bound).

    Returns:
        ``(B, H, W)`` bool: pixel centres covered by at least one triangle.

    Example:
        >>> pix = torch.tensor([[[1.0, 1.0], [8.0, 1.0], [1.0, 8.0]]])
        >>> rasterize_mask(pix, torch.ones(1, 3), torch.tensor([[0, 1, 2]]), 10, 10).sum()
        tensor(36)
    """
    _check_inputs(pixels, depth, faces)
    B = pixels.shape[0]
    out = torch.zeros(B * height * width, dtype=torch.bool, device=pixels.device)
    if B == 0 or faces.shape[0] == 0:
        return out.reshape(B, height, width)
    per = _estimate_candidates(pixels, faces, width, height)
    for a, b in _chunks(B, per, budget):
        cand = _candidates(pixels[a:b], depth[a:b], faces, width, height, eps=_eps(pixels))
        loc = ((cand.image + a) * height + cand.y) * width + cand.x
        out[loc] = True
    return out.reshape(B, height, width)


@dataclass
class ZBuffer:
    """Result of :func:`rasterize_zbuffer`.

    Attributes:
        depth: ``(B, H, W)`` camera depth of the nearest surface (``inf`` where empty).
        face: ``(B, H, W)`` long, index of the visible face (``-1`` where empty).
        bary: ``(B, H, W, 3)`` perspective-correct barycentric coordinates of the visible point
            in its face (zeros where empty).
    """

    depth: Tensor
    face: Tensor
    bary: Tensor

    @property
    def mask(self) -> Tensor:
        """``(B, H, W)`` bool coverage."""
        return self.face >= 0


def rasterize_zbuffer(pixels: Tensor, depth: Tensor, faces: Tensor, width: int, height: int,
                      budget: int = 4_000_000) -> ZBuffer:
    """Nearest visible face, its depth and barycentrics per pixel.

    Args: as :func:`rasterize_mask`.

    Returns:
        a :class:`ZBuffer`. Depth is perspective-correct (``1/z`` interpolated in screen space),
        so back-projecting a pixel with its depth gives a point on the visible triangle.
    """
    _check_inputs(pixels, depth, faces)
    if faces.shape[0] >= 1 << _FACE_BITS:
        raise ValueError(f"faces: at most {1 << _FACE_BITS} faces supported, got "
                         f"{faces.shape[0]}")
    B, dev = pixels.shape[0], pixels.device
    big = torch.iinfo(torch.int64).max
    key = torch.full((B * height * width,), big, dtype=torch.int64, device=dev)
    per = _estimate_candidates(pixels, faces, width, height) if B else 1.0
    for a, b in _chunks(B, per, budget):
        cand = _candidates(pixels[a:b], depth[a:b], faces, width, height, eps=_eps(pixels))
        z = 1.0 / (cand.bary * cand.inv_z).sum(-1).clamp_min(1e-12)
        zq = torch.round(z.double() * _DEPTH_SCALE).long().clamp(0, (1 << 40) - 1)
        loc = ((cand.image + a) * height + cand.y) * width + cand.x
        key.scatter_reduce_(0, loc, (zq << _FACE_BITS) | cand.face, "amin", include_self=True)
    hit = key != big
    face = torch.where(hit, key & ((1 << _FACE_BITS) - 1), torch.full_like(key, -1))
    # exact depth and perspective-correct barycentrics of the winners
    loc = hit.nonzero().squeeze(-1)
    img = torch.div(loc, height * width, rounding_mode="floor")
    rem = loc - img * height * width
    yy = torch.div(rem, width, rounding_mode="floor")
    xx = rem - yy * width
    f = face[loc]
    tri = pixels[img[:, None], faces[f]]  # (N, 3, 2)
    zv = depth[img[:, None], faces[f]].clamp_min(_NEAR)  # (N, 3)
    p = torch.stack([xx, yy], -1).to(tri.dtype)
    v0, v1, v2 = tri.unbind(-2)
    area = (v1[:, 0] - v0[:, 0]) * (v2[:, 1] - v0[:, 1]) - (v2[:, 0] - v0[:, 0]) * \
        (v1[:, 1] - v0[:, 1])

    def edge(a: Tensor, b: Tensor) -> Tensor:
        return (b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1]) - (p[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])

    lam = torch.stack([edge(v1, v2), edge(v2, v0), edge(v0, v1)], -1) / area[:, None]
    wz = lam / zv
    zz = 1.0 / wz.sum(-1)
    bary_p = wz * zz[:, None]
    depth_out = torch.full((B * height * width,), math.inf, dtype=pixels.dtype, device=dev)
    depth_out[loc] = zz
    bary = torch.zeros(B * height * width, 3, dtype=pixels.dtype, device=dev)
    bary[loc] = bary_p
    return ZBuffer(depth_out.reshape(B, height, width), face.reshape(B, height, width),
                   bary.reshape(B, height, width, 3))


# --------------------------------------------------------------------------- mesh helpers


def face_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """Unit normals ``(*, F, 3)`` of triangles (right-hand rule on the vertex order)."""
    v = vertices[..., faces, :]  # (*, F, 3, 3)
    n = torch.linalg.cross(v[..., 1, :] - v[..., 0, :], v[..., 2, :] - v[..., 0, :])
    return torch.nn.functional.normalize(n, dim=-1, eps=1e-12)


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """Area-weighted unit vertex normals ``(*, V, 3)``."""
    v = vertices[..., faces, :]
    n = torch.linalg.cross(v[..., 1, :] - v[..., 0, :], v[..., 2, :] - v[..., 0, :])
    out = torch.zeros_like(vertices)
    idx = faces.reshape(-1)
    nn3 = n[..., :, None, :].expand(*n.shape[:-1], 3, 3).reshape(*n.shape[:-2], -1, 3)
    out.index_add_(out.dim() - 2, idx, nn3)
    return torch.nn.functional.normalize(out, dim=-1, eps=1e-12)


def capsule_mesh(endpoints: Tensor, radii: Tensor, sections: int = 12, rings: int = 3
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """Closed triangle meshes of capsules, batched over poses.

    Args:
        endpoints: ``(*, K, 2, 3)`` capsule axis end points.
        radii: ``(K,)`` radii.
        sections: vertices around the axis.
        rings: latitude rings per hemispherical cap (excluding the pole).

    Returns:
        ``vertices (*, K·Vc, 3)``, ``faces (K·Fc, 3)`` (shared by every pose) and
        ``face_capsule (K·Fc,)`` (index of the capsule each face belongs to).
    """
    if endpoints.shape[-2:] != (2, 3):
        raise ValueError(f"endpoints: expected shape (*, K, 2, 3), got {tuple(endpoints.shape)}")
    K = endpoints.shape[-3]
    if radii.shape != (K,):
        raise ValueError(f"radii: expected shape ({K},), got {tuple(radii.shape)}")
    dt, dev = endpoints.dtype, endpoints.device
    a, b = endpoints[..., 0, :], endpoints[..., 1, :]
    axis = b - a
    length = axis.norm(dim=-1, keepdim=True)
    e = torch.where(length > 1e-9, axis / length.clamp_min(1e-9),
                    torch.tensor([0.0, 0.0, 1.0], dtype=dt, device=dev))
    helper = torch.where(e[..., :1].abs() < 0.9, torch.tensor([1.0, 0, 0], dtype=dt, device=dev),
                         torch.tensor([0.0, 1, 0], dtype=dt, device=dev))
    u = torch.nn.functional.normalize(torch.linalg.cross(e, helper), dim=-1)
    v = torch.linalg.cross(e, u)
    # latitude rings from the bottom pole (end a) to the top pole (end b)
    beta = torch.linspace(0, math.pi / 2, rings + 1, dtype=dt, device=dev)  # 0 = equator
    lat = torch.cat([-beta.flip(0), beta])  # (2R+2,), elevation, -pi/2 .. pi/2
    end = torch.cat([torch.zeros(rings + 1), torch.ones(rings + 1)]).to(dt).to(dev)
    phi = torch.arange(sections, dtype=dt, device=dev) * (2 * math.pi / sections)
    cl, sl = torch.cos(lat)[:, None], torch.sin(lat)[:, None]  # (L, 1)
    cp, sp = torch.cos(phi)[None], torch.sin(phi)[None]  # (1, S)
    r = radii.to(dt)[:, None, None, None]  # (K, 1, 1, 1)
    base = a[..., None, None, :] + end[:, None, None] * axis[..., None, None, :]  # (*, K, L, 1, 3)
    dirs = (cl * cp)[..., None] * u[..., None, None, :] + (cl * sp)[..., None] * \
        v[..., None, None, :] + (sl * torch.ones_like(cp))[..., None] * e[..., None, None, :]
    verts = base + r * dirs  # (*, K, L, S, 3)
    L = lat.shape[0]
    verts = verts.reshape(*verts.shape[:-4], K * L * sections, 3)
    # faces between consecutive rings
    i = torch.arange(L - 1, device=dev)[:, None]
    j = torch.arange(sections, device=dev)[None]
    jn = (j + 1) % sections
    q00, q01 = i * sections + j, i * sections + jn
    q10, q11 = (i + 1) * sections + j, (i + 1) * sections + jn
    f = torch.cat([torch.stack([q00, q01, q11], -1).reshape(-1, 3),
                   torch.stack([q00, q11, q10], -1).reshape(-1, 3)])  # (Fc, 3)
    Vc = L * sections
    offs = torch.arange(K, device=dev)[:, None, None] * Vc
    faces = (f[None] + offs).reshape(-1, 3)
    face_capsule = torch.arange(K, device=dev).repeat_interleave(f.shape[0])
    return verts, faces, face_capsule
