"""Capsules fitted to a body mesh: the tracker's capsule skin with a subject's girths.

A :class:`~torchmocap.body.CapsuleBody` has one capsule per skeleton bone (parent joint → child
joint). Given one mesh of a body posed by the same skeleton (any pose, the rest pose included),
each vertex belongs to a capsule: by a label (e.g.
:meth:`~torchmocap.body.ParametricBody.capsule_labels`, from the mesh's own bones) or, given
the joint carrying each vertex, by the nearest axis among the capsules that joint moves. Each
capsule's radius is the least-squares fit of its surface's distance to the capsule's side::

    r_b = argmin_r Σ_{v ∈ b} a_v (ρ_v − r)² = Σ a_v ρ_v / Σ a_v

(``ρ_v`` the distance of vertex ``v`` to the bone's axis, over the vertices that project inside
it; ``a_v`` the vertex's share of the surface area when the faces are given, else 1). A capsule
at an end site (head top, hand, toe) ends where its surface ends (``fit_ends``: the cap's tip at
the 99th percentile along the axis, possibly beyond the end site), or a radius before the end
site as :class:`~torchmocap.body.CapsuleBody` does. With ``axis_offsets`` (default) the axes
also move off their bones, perpendicular to them (a vector in the parent joint's frame, as
:class:`~torchmocap.body.CapsuleBody` takes it): the offsets minimise the same sum of squares
(Gauss-Newton, the radius profiled out) with a small pull towards 0 and a bound on their length.
A few fixed-point rounds alternate offsets, radii and ends. The radii are differentiable w.r.t.
the vertices (the assignment, the ends and the offsets are not).

This is the fast path by which a fitted body keeps the capsule likelihood's speed.

Shapes: ``V`` vertices, ``F`` faces, ``B`` bones (capsules), ``J`` joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchmocap.body.capsules import CapsuleBody, capsule_endpoints, segment_distance

__all__ = ["CapsuleFit", "assign_to_capsules", "capsule_radii", "fit_capsules", "vertex_areas"]


@dataclass
class CapsuleFit:
    """Result of :func:`fit_capsules`.

    Attributes:
        body: the fitted :class:`~torchmocap.body.CapsuleBody`.
        radii: ``(B,)`` fitted radii (differentiable w.r.t. the vertices; the default radius
            where a capsule got no vertex).
        axis_offsets: ``(B, 3)`` offsets in the parent joints' frames (zeros unless fitted).
        assignment: ``(V,)`` long, the capsule of every vertex (−1: none of its carrier's).
        rms: ``(B,)`` root-mean-square distance of each capsule's vertices to its surface (m).
        counts: ``(B,)`` vertices per capsule.
        fitted: ``(B,)`` bool, capsules whose radius was fitted (else the anthropometric
            default: too few vertices, or too little of the axis covered).
    """

    body: CapsuleBody
    radii: Tensor
    axis_offsets: Tensor
    assignment: Tensor
    rms: Tensor
    counts: Tensor
    fitted: Tensor


def _carrier(joint: int, parents: list[int], carrying: set[int]) -> int:
    j = joint
    while j >= 0 and j not in carrying:
        j = parents[j]
    return j


def assign_to_capsules(vertices: Tensor, parts: Tensor, endpoints: Tensor,
                       parent_index: Tensor, parents: list[int]) -> Tensor:
    """The capsule ``(V,)`` of every vertex: the nearest axis among the capsules whose parent
    joint is carried by the vertex's carrier joint ``parts (V,)`` (−1 where there is none).

    Args:
        vertices: ``(V, 3)``; endpoints ``(B, 2, 3)`` capsule axes of the same pose.
        parent_index: ``(B,)`` parent joint of every capsule; parents: the skeleton's parents.
    """
    carrying = {int(p) for p in parts.unique()}
    owner = torch.tensor([_carrier(int(p), parents, carrying) for p in parent_index.tolist()],
                         device=vertices.device)  # (B,) carrier joint of every capsule
    d = segment_distance(vertices.detach(), endpoints.detach())  # (V, B)
    allowed = owner[None, :] == parts.to(vertices.device)[:, None]
    d = torch.where(allowed, d, torch.full_like(d, float("inf")))
    best = d.argmin(-1)
    return torch.where(allowed.any(-1), best, torch.full_like(best, -1))


def vertex_areas(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V,)`` a third of the area of the triangles ``faces (F, 3)`` around each vertex."""
    t = vertices[faces]  # (F, 3, 3)
    area = torch.linalg.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]).norm(dim=-1) / 2
    return torch.zeros(vertices.shape[0], dtype=vertices.dtype,
                       device=vertices.device).index_add(0, faces.reshape(-1),
                                                         (area / 3).repeat_interleave(3))


def _weighted_quantile(x: Tensor, w: Tensor, q: float) -> Tensor:
    order = x.argsort()
    c = w[order].cumsum(0)
    k = torch.searchsorted(c, q * c[-1]).clamp(max=x.numel() - 1)
    return x[order][k]


def fit_capsules(skeleton: nn.Module, vertices: Tensor, theta: Tensor | None = None,
                 labels: Tensor | None = None, parts: Tensor | None = None,
                 faces: Tensor | None = None, axis_offsets: bool = True,
                 offset_bones: list[str] | None = None, fit_ends: bool = True,
                 rounds: int = 4, offset_prior: float = 1e-2, max_offset: float = 0.06,
                 end_quantile: float = 0.99, min_coverage: float = 0.4) -> CapsuleFit:
    """Fit a :class:`~torchmocap.body.CapsuleBody`'s radii (and optionally axis offsets and
    the ends of the capsules at end sites) to a body mesh posed by ``skeleton`` (module
    docstring).

    Args:
        skeleton: the skeleton that posed the mesh (its offsets are the body's).
        vertices: ``(V, 3)`` one posed mesh (metres).
        theta: ``(D,)`` the mesh's pose (default: the rest pose).
        labels: ``(V,)`` long, the capsule (bone index in ``CapsuleBody`` order, −1 none) of
            each vertex, e.g. :meth:`~torchmocap.body.ParametricBody.capsule_labels`; or
        parts: ``(V,)`` long, the skeleton joint carrying each vertex: each vertex then goes
            to the nearest axis among its carrier's capsules.
        faces: ``(F, 3)`` the mesh's triangles: vertices are weighted by their area (the fit
            is then of the surface, not of the vertex density: a face has more vertices per
            cm² than a back); default: equal weights.
        axis_offsets: also fit axis offsets (of ``offset_bones``, default every capsule),
            perpendicular to the bones (default; against the Anny body's meshes they raise the
            silhouette IoU from ~0.80 to ~0.84: a belly, a face, a hip in front of its bone).
        fit_ends: move the end of every capsule at an end site (head top, hands, toes) so its
            cap's tip reaches the ``end_quantile`` of its surface along the axis
            (``end_shrink``, negative: beyond the end site); else the capsule ends a radius
            before the site, as :class:`~torchmocap.body.CapsuleBody` does.
        rounds: fixed-point rounds (assignment, offsets, radius, ends).
        offset_prior: weight of ``‖offset‖²`` (m²) against the mean squared distance.
        max_offset: bound of an offset's length (metres; also at most half the capsule's mean
            distance: a flat part, a hand, would otherwise slide its axis far away).
        min_coverage: a capsule whose surface spans less than this fraction of its axis (10th
            to 90th percentile, e.g. the clavicle's few vertices at the shoulder) keeps its
            anthropometric radius.

    Returns:
        :class:`CapsuleFit` (its ``body.end_shrink`` holds the fitted ends).

    Raises:
        ValueError: naming ``vertices``/``labels``/``parts``/``faces``/``theta`` on a wrong
            shape or index.

    Example:
        >>> from torchmocap.skeleton import human31
        >>> sk = human31()
        >>> cap = CapsuleBody(sk)
        >>> pts, _, bone = cap.sample_surface_points(sk(sk.zero_pose()), 4000,
        ...                                          torch.Generator().manual_seed(0))
        >>> fit = fit_capsules(sk, pts, labels=bone, fit_ends=False, min_coverage=0.0)
        >>> bool((fit.radii - cap.radii).abs().max() < 0.01)
        True
    """
    if vertices.dim() != 2 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices: expected one mesh (V, 3), got {tuple(vertices.shape)}")
    if (labels is None) == (parts is None):
        raise ValueError("labels: pass exactly one of labels (capsule per vertex) or parts "
                         "(carrier joint per vertex)")
    dt, dev = vertices.dtype, vertices.device
    default = CapsuleBody(skeleton).to(dev)
    B, J, V = default.num_bones, skeleton.num_joints, vertices.shape[0]
    for name, idx, lo, hi in (("labels", labels, -1, B), ("parts", parts, 0, J),
                              ("faces", faces, 0, V)):
        if idx is None:
            continue
        shape_ok = idx.shape == (V,) if name != "faces" else (idx.dim() == 2 and
                                                              idx.shape[1] == 3)
        if not shape_ok or idx.dtype not in (torch.int32, torch.int64):
            want = f"({V},)" if name != "faces" else "(F, 3)"
            raise ValueError(f"{name}: expected {want} indices, got {tuple(idx.shape)} "
                             f"{idx.dtype}")
        if bool(((idx < lo) | (idx >= hi)).any()):
            raise ValueError(f"{name}: indices must lie in [{lo}, {hi})")
    theta = skeleton.zero_pose(dtype=dt, device=dev) if theta is None else theta.to(dt)
    if theta.shape != (skeleton.num_dofs,):
        raise ValueError(f"theta: expected one pose ({skeleton.num_dofs},), got "
                         f"{tuple(theta.shape)}")
    kin = skeleton(theta)
    names = default.bone_names
    leaf = (default.end_shrink > 0).to(dev)
    w = vertex_areas(vertices.detach(), faces.to(dev)) if faces is not None else \
        torch.ones(V, dtype=dt, device=dev)
    radii = default.radii.to(dt)
    shrink = torch.where(leaf, radii, torch.zeros_like(radii))
    offsets = torch.zeros(B, 3, dtype=dt, device=dev)
    fit_off = torch.zeros(B, dtype=torch.bool, device=dev)
    if axis_offsets:
        chosen = names if offset_bones is None else offset_bones
        unknown = sorted(set(chosen) - set(names))
        if unknown:
            raise ValueError(f"offset_bones: unknown bone(s) {unknown}; bones: {names}")
        fit_off[[names.index(b) for b in chosen]] = True
    R_parent = kin.rotations[default.parent_index].to(dt)  # (B, 3, 3)

    def axes(end_shrink: Tensor, off: Tensor) -> Tensor:  # offsets in the world frame
        local = (R_parent.transpose(-1, -2) @ off[..., None])[..., 0]
        return capsule_endpoints(kin.positions.to(dt), default.parent_index,
                                 default.child_index, end_shrink, kin.rotations.to(dt), local)

    assign = labels.to(dev) if labels is not None else None
    fitted = torch.zeros(B, dtype=torch.bool, device=dev)
    counts = torch.zeros(B, dtype=torch.long, device=dev)
    for _ in range(max(1, rounds)):
        if parts is not None:
            assign = assign_to_capsules(vertices, parts.to(dev),
                                        axes(shrink.detach(), offsets.detach()),
                                        default.parent_index, list(skeleton.parents))
        counts = torch.bincount(assign[assign >= 0], minlength=B)
        if axis_offsets:
            offsets = _fit_offsets(vertices, w, assign, axes, shrink.detach(), offsets.detach(),
                                   fit_off & (counts >= 8), offset_prior, max_offset)
        full = axes(torch.zeros_like(shrink), offsets.detach())  # (B, 2, 3), unshrunk
        radii, fitted, tips = _fit_radii(vertices, w, assign, full,
                                         shrink.detach(), default.radii.to(dt), min_coverage,
                                         end_quantile)
        length = (full[:, 1] - full[:, 0]).norm(dim=-1)
        if fit_ends:
            end = torch.minimum(length, (tips - radii.detach()))
            shrink = torch.where(leaf & fitted, length - end, torch.where(
                leaf, radii.detach(), torch.zeros_like(shrink)))
        else:
            shrink = torch.where(leaf, radii.detach(), torch.zeros_like(shrink))
    ep = axes(shrink, offsets.detach())
    d = segment_distance(vertices.detach(), ep)
    own = d.gather(-1, assign.clamp_min(0)[:, None])[:, 0] - radii.detach()[assign.clamp_min(0)]
    wa = w * (assign >= 0).to(dt)
    sq = torch.zeros(B, dtype=dt, device=dev).index_add(0, assign.clamp_min(0), own.square() * wa)
    wsum = torch.zeros(B, dtype=dt, device=dev).index_add(0, assign.clamp_min(0), wa)
    rms = (sq / wsum.clamp_min(1e-12)).sqrt()
    local = (R_parent.transpose(-1, -2) @ offsets.detach()[..., None])[..., 0]
    body = CapsuleBody(skeleton, radii={n: float(r) for n, r in zip(names, radii.tolist())},
                       axis_offsets={n: local[b].tolist() for b, n in enumerate(names)
                                     if bool(fit_off[b])} or None).to(dev)
    body.end_shrink.copy_(shrink.detach().to(body.end_shrink))
    return CapsuleFit(body, radii, local, assign, rms, counts, fitted)


def capsule_radii(vertices: Tensor, areas: Tensor, fit: CapsuleFit, axes: Tensor,
                  min_coverage: float = 0.4) -> Tensor:
    """The radii ``(B,)`` of a fit's capsules for other vertices ``(V, 3)`` of the same mesh
    (e.g. another phenotype of one body), with the fit's assignment, unshrunk ``axes (B, 2, 3)``
    (its axis offsets applied) and ends kept: the area-weighted (``areas (V,)``) mean distance
    of each capsule's skin to its axis, differentiable w.r.t. the vertices; capsules the fit left
    at their default keep the fit's radius."""
    radii, _, _ = _fit_radii(vertices, areas, fit.assignment, axes,
                             fit.body.end_shrink.to(vertices.dtype), fit.radii.detach(),
                             min_coverage, 0.99)
    return torch.where(fit.fitted, radii, fit.radii.detach().to(radii))


def _fit_radii(vertices: Tensor, w: Tensor, assign: Tensor, full: Tensor, shrink: Tensor,
               default: Tensor, min_coverage: float, quantile: float
               ) -> tuple[Tensor, Tensor, Tensor]:
    """Per capsule: the area-weighted mean distance of its surface to its axis over the part
    that projects inside the (shrunk) axis (the cylinder; all of it if too little does),
    whether it was fitted, and the ``quantile`` of its surface along the full axis."""
    B = full.shape[0]
    a, ab = full[:, 0], full[:, 1] - full[:, 0]
    length = ab.norm(dim=-1).clamp_min(1e-9)
    u = ab / length[:, None]
    radii, fitted, tips = default.clone(), torch.zeros(B, dtype=torch.bool), default.clone()
    radii = radii.to(vertices.dtype)
    out_r = []
    for b in range(B):
        sel = assign == b
        if int(sel.sum()) < 8:
            out_r.append(default[b])
            continue
        x, wb = vertices[sel], w[sel]
        rel = x - a[b]
        t = rel @ u[b]
        lo, hi = _weighted_quantile(t.detach(), wb, 0.1), _weighted_quantile(t.detach(), wb, 0.9)
        tips[b] = _weighted_quantile(t.detach(), wb, quantile)
        if float((hi - lo) / length[b]) < min_coverage:
            out_r.append(default[b])
            continue
        inside = (t >= 0) & (t <= length[b] - shrink[b].clamp_min(0))
        if int(inside.sum()) >= 8:
            radial = (rel - t[:, None] * u[b]).norm(dim=-1)
            r = (radial[inside] * wb[inside]).sum() / wb[inside].sum()
        else:
            end = a[b] + (length[b] - shrink[b]).clamp_min(0) * u[b]
            d = segment_distance(x, torch.stack([a[b], end])[None])[:, 0]
            r = (d * wb).sum() / wb.sum()
        out_r.append(r)
        fitted[b] = True
    return torch.stack(out_r).to(vertices.dtype), fitted.to(vertices.device), tips


def _fit_offsets(vertices: Tensor, w: Tensor, assign: Tensor, axes, shrink: Tensor,
                 offsets: Tensor, free: Tensor, prior: float, max_offset: float,
                 steps: int = 6) -> Tensor:
    """Gauss-Newton steps on the world-frame offsets of the ``free`` capsules, perpendicular to
    their axes (a move along the axis is the ends' business): per capsule, minimise the
    weighted mean of (d_v(o) − mean d(o))² + prior ‖o‖² (the radius profiled out)."""
    if not bool(free.any()):
        return offsets
    keep = assign >= 0
    x, a, wv = vertices.detach()[keep], assign[keep], w[keep]
    B = offsets.shape[0]
    dt, dev = x.dtype, x.device
    n = torch.zeros(B, dtype=dt, device=dev).index_add(0, a, wv).clamp_min(1e-12)
    o = offsets.clone()
    eye = torch.eye(3, dtype=dt, device=dev)
    with torch.no_grad():
        for _ in range(steps):
            ep = axes(shrink, o)
            d = segment_distance(x, ep).gather(-1, a[:, None])[:, 0]  # (N,)
            ab = ep[:, 1] - ep[:, 0]
            u = ab / ab.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            perp = eye - u[:, :, None] * u[:, None, :]  # (B, 3, 3)
            # per-vertex Jacobian of d w.r.t. its capsule's offset: minus the unit vector from
            # the closest axis point to the vertex (the whole axis moves by o)
            abv = ab[a]
            t = (((x - ep[a, 0]) * abv).sum(-1) / (abv * abv).sum(-1).clamp_min(1e-12)).clamp(0, 1)
            closest = ep[a, 0] + t[:, None] * abv
            jac = -(x - closest) / d.clamp_min(1e-9)[:, None]  # (N, 3)
            mean_d = torch.zeros(B, dtype=dt, device=dev).index_add(0, a, wv * d) / n
            mean_j = torch.zeros(B, 3, dtype=dt, device=dev).index_add(
                0, a, wv[:, None] * jac) / n[:, None]
            r = d - mean_d[a]  # residuals with the radius profiled out
            jc = ((jac - mean_j[a])[:, None, :] @ perp[a])[:, 0]  # perpendicular part
            H = torch.zeros(B, 3, 3, dtype=dt, device=dev).index_add(
                0, a, wv[:, None, None] * jc[:, :, None] * jc[:, None, :]) / n[:, None, None]
            rhs = torch.zeros(B, 3, dtype=dt, device=dev).index_add(
                0, a, wv[:, None] * jc * r[:, None]) / n[:, None]
            H = perp @ H @ perp + prior * eye
            step = torch.linalg.solve(H, -(perp @ (rhs + prior * o)[..., None]))[..., 0]
            step = (perp @ step[..., None])[..., 0].clamp(-0.02, 0.02)
            new = o + step
            # a flat part (a hand) has a degenerate far-away axis of nearly equal distances:
            # the offset stays within ``max_offset`` and half the current mean distance
            bound = torch.minimum(torch.full_like(mean_d, max_offset), 0.5 * mean_d)
            norm = new.norm(dim=-1).clamp_min(1e-12)
            new = new * (bound / norm).clamp(max=1.0)[:, None]
            o = torch.where(free[:, None], new, o)
    return o
