"""Kinematic flips of a link under perspective projection (Sminchisescu & Triggs 2003, §3).

A link from a parent joint ``P`` to a child joint ``X`` of length ``L`` is seen by a camera with
centre ``c``. The child lies on the camera ray ``c + s d`` (``d = unit(X - c)``, ``s > 0``) through
its image point; every point of that ray at distance ``L`` from ``P`` projects to the same pixel
and keeps the bone length. The ray meets the sphere ``|x - P| = L`` twice in general: at the
current child and at its *flip* (the link turned towards / away from the camera).

Numerics (REFERENCE §7). With ``m = P - o`` for a point ``o`` on the ray, ``t = d.m`` and
``e = m - t d`` (the perpendicular from the ray to ``P``), the discriminant is the stable
``Delta = L^2 - |e|^2``; the roots are ``lambda+- = t +- sqrt(Delta)`` (measured from ``o``).
The naive ``t^2 - |m|^2 + L^2`` subtracts two numbers of size ``|m|^2`` and gets the sign of
``Delta`` wrong in about a third of float32 cases with ``|Delta| = 1e-5 L^2`` and the camera
3-6 m away; the stable form gets all of them right. Its remaining error is of the order of the
unit round-off times ``|m| L``, so the functions here anchor the ray at the child (``o = X``,
``|m| ~ L``) rather than at the camera centre (``|m|`` ~ metres): about 7x fewer wrong signs
at ``|Delta| = 1e-6 L^2``. No float32 method resolves ``|Delta| ~ 1e-7 L^2``: rounding the
inputs to float32 already changes ``Delta`` by that much.

The flip with the current bone length needs no square root at all: it is the reflection of the
bone in the plane through ``P`` orthogonal to the ray, ``X' = X + 2 (d.(P - X)) d`` — the length
is kept exactly and ``X' - X`` is parallel to the ray.

Example:
    >>> c = torch.zeros(3); P = torch.tensor([0.0, 0.0, 3.0]); X = torch.tensor([0.3, 0.0, 3.0])
    >>> flipped, valid = flip_child(P, X, c)
    >>> flipped.shape, bool(valid)
    (torch.Size([3]), True)
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from torchmocap.geometry._checks import check_finite, check_last_dims

__all__ = [
    "RaySphereIntersection",
    "ray_sphere_intersections",
    "ray_sphere_discriminant",
    "flip_child",
]


class RaySphereIntersection(NamedTuple):
    """Intersections of the line ``o + lambda d`` (``d`` unit) with a sphere.

    Attributes:
        lam_minus: ``(*)`` nearer root ``t - sqrt(Delta)`` along the unit direction (metres from
            the origin; negative = behind the origin). Where the line misses it is ``t``, the
            point of closest approach.
        lam_plus: ``(*)`` farther root ``t + sqrt(Delta)`` (``t`` on a miss).
        hit: ``(*)`` bool, ``Delta >= 0`` (the line meets the sphere).
    """

    lam_minus: torch.Tensor
    lam_plus: torch.Tensor
    hit: torch.Tensor


def _safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    """``sqrt(max(x, 0))`` with a zero (not infinite/NaN) gradient at and below 0."""
    pos = x > 0
    return torch.where(pos, torch.where(pos, x, torch.ones_like(x)).sqrt(), torch.zeros_like(x))


def _unit(v: torch.Tensor, name: str) -> torch.Tensor:
    n = v.norm(dim=-1, keepdim=True)
    if v.numel() and not bool((n > 0).all()):
        raise ValueError(f"{name}: expected non-zero vectors (a ray needs a direction)")
    return v / n


def _as_radius(radius: torch.Tensor | float, like: torch.Tensor) -> torch.Tensor:
    r = torch.as_tensor(radius, dtype=like.dtype, device=like.device)
    check_finite(r, "radius")
    if r.numel() and not bool((r >= 0).all()):
        raise ValueError("radius: expected values >= 0")
    return r


def ray_sphere_discriminant(
    origin: torch.Tensor,
    direction: torch.Tensor,
    sphere_center: torch.Tensor,
    radius: torch.Tensor | float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Stable discriminant ``Delta = r^2 - |e|^2`` and closest-approach parameter ``t``.

    No input checks (internal building block of :func:`ray_sphere_intersections`): ``direction``
    must be unit, all shapes broadcastable ``(*, 3)`` / ``(*)``.

    Returns:
        ``delta (*)`` in metres^2 and ``t (*)`` in metres along ``direction`` from ``origin``.
    """
    m = sphere_center - origin
    t = (direction * m).sum(-1)
    e = m - t[..., None] * direction
    delta = radius * radius - (e * e).sum(-1)
    return delta, t


def ray_sphere_intersections(
    origin: torch.Tensor,
    direction: torch.Tensor,
    sphere_center: torch.Tensor,
    radius: torch.Tensor | float,
) -> RaySphereIntersection:
    """Where the line ``origin + lambda d`` meets the sphere ``|x - sphere_center| = radius``.

    Uses the stable discriminant ``Delta = r^2 - |e|^2`` (module docstring). For the best float32
    accuracy pass an ``origin`` near the sphere (e.g. a known point on the ray such as the
    observed child joint), not a far camera centre.

    Args:
        origin: ``(*, 3)`` a point of the line (metres).
        direction: ``(*, 3)`` non-zero direction; normalised here, so ``lambda`` is in metres.
        sphere_center: ``(*, 3)`` metres.
        radius: ``(*)`` or a float, metres, ``>= 0``.

    Returns:
        :class:`RaySphereIntersection` with ``(*)`` fields (``*`` = the broadcast batch shape).
        Differentiable (away from tangency, where the root's derivative is infinite; the
        gradient of ``sqrt(Delta)`` is set to 0 at ``Delta <= 0``). Never NaN for finite input.

    Example:
        >>> r = ray_sphere_intersections(torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]),
        ...                              torch.tensor([0.0, 0.1, 3.0]), 0.3)
        >>> r.lam_minus < r.lam_plus, bool(r.hit)
        (tensor(True), True)
    """
    check_last_dims(origin, (3,), "origin")
    check_last_dims(direction, (3,), "direction")
    check_last_dims(sphere_center, (3,), "sphere_center")
    for x, n in ((origin, "origin"), (direction, "direction"), (sphere_center, "sphere_center")):
        check_finite(x, n)
    d = _unit(direction, "direction")
    r = _as_radius(radius, origin)
    delta, t = ray_sphere_discriminant(origin, d, sphere_center, r)
    root = _safe_sqrt(delta)
    return RaySphereIntersection(t - root, t + root, delta >= 0)


def flip_child(
    parent: torch.Tensor,
    child: torch.Tensor,
    camera_center: torch.Tensor,
    length: torch.Tensor | float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The kinematic flip of a child joint about its camera ray (Sminchisescu & Triggs, Fig. 1).

    With ``length=None`` the bone keeps its current length ``|child - parent|`` and the flip is
    the reflection ``X' = X + 2 (d.(P - X)) d``, ``d = unit(X - c)`` (the other root
    ``c + (2 t_c - lambda) d`` of REFERENCE §7 in a form free of cancellation). With a ``length``
    the child is re-attached at that distance: the result is the root of the ray–sphere
    intersection on the other side of the closest approach to ``parent`` than ``child``; a ray
    that misses the sphere (``Delta < 0``) gives ``valid = False`` and the closest point.

    Flipping twice returns the original child (same ray, same sphere).

    Args:
        parent: ``(*, 3)`` parent joint position (metres, world).
        child: ``(*, 3)`` child joint position; must differ from ``camera_center``.
        camera_center: ``(*, 3)`` optical centre (e.g. :meth:`CameraRig.camera_centers`).
        length: optional ``(*)`` or float bone length in metres (``>= 0``).

    Returns:
        ``flipped (*, 3)`` and ``valid (*)`` bool: the ray meets the sphere and the flipped child
        is in front of the camera (positive depth along the ray).

    Example:
        >>> P = torch.tensor([[0.0, 0.0, 3.0]]); X = torch.tensor([[0.2, 0.0, 3.2]])
        >>> flip_child(P, X, torch.zeros(3))[0].shape
        torch.Size([1, 3])
    """
    check_last_dims(parent, (3,), "parent")
    check_last_dims(child, (3,), "child")
    check_last_dims(camera_center, (3,), "camera_center")
    for x, n in ((parent, "parent"), (child, "child"), (camera_center, "camera_center")):
        check_finite(x, n)
    ray = child - camera_center
    n = ray.norm(dim=-1, keepdim=True)
    if ray.numel() and not bool((n > 0).all()):
        raise ValueError("child: coincides with camera_center (no camera ray)")
    d = ray / n
    depth = n[..., 0]  # depth of the child along the ray
    if length is None:
        t = (d * (parent - child)).sum(-1)  # closest approach, from the child
        shift = 2 * t
        valid = depth + shift > 0
        return child + shift[..., None] * d, valid
    r = _as_radius(length, child)
    delta, t = ray_sphere_discriminant(child, d, parent, r)
    root = _safe_sqrt(delta)
    # the child sits at lambda = 0: take the root on the other side of t
    lam = torch.where(t >= 0, t + root, t - root)
    valid = (delta >= 0) & (depth + lam > 0)
    return child + lam[..., None] * d, valid
