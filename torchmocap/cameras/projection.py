"""Functional pinhole + Brown–Conrady camera model (OpenCV conventions), batched over cameras.

Conventions (OpenCV): world-to-camera ``x_cam = R @ x_world + t``; the camera looks along its
+z axis, image x to the right, image y down; pixel ``(u, v)`` with integer pixel *centres*
(``(0, 0)`` is the centre of the top-left pixel — Bouguet's toolbox uses the same origin);
distortion coefficients ``(k1, k2, p1, p2, k3)`` in OpenCV order (Bouguet's ``kc`` is the same
order). Image sizes are ``(width, height)``.

Shapes: ``C`` cameras, ``N`` points, ``*`` arbitrary leading batch dims. Points to project are
``(*, N, 3)`` and come out per camera as ``(*, C, N, 2)``.

Distortion and undistortion use :func:`kornia.geometry.calibration.distort_points` /
:func:`kornia.geometry.calibration.undistort_points` (tested against the closed form in
``tests/cameras``). kornia's undistortion is a fixed-point iteration whose default of 5 steps
leaves ~0.02 px error at the corners of a 640×480 lens with k1 = −0.32; we use 20 steps
(< 1e-9 px there).
"""

from __future__ import annotations

import torch
from kornia.geometry.calibration import distort_points as _kornia_distort
from kornia.geometry.calibration import undistort_points as _kornia_undistort
from torch import Tensor

__all__ = [
    "backproject_pixels",
    "camera_centers",
    "distort_normalized",
    "intrinsics_matrix",
    "look_at",
    "max_monotonic_radius",
    "project_points",
    "project_points_planar",
    "world_to_camera",
]

_DEPTH_EPS = 1e-6


def _check_last(name: str, x: Tensor, shape: tuple[int, ...]) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    n = len(shape)
    if x.dim() < n or tuple(x.shape[-n:]) != shape:
        raise ValueError(f"{name} must have shape (*, {', '.join(map(str, shape))}), got "
                         f"{tuple(x.shape)}")


class CameraError(ValueError):
    """Malformed camera parameters or calibration file (names the file and line when known)."""


class RefinementError(CameraError):
    """A camera refinement that cannot run as asked (names the argument or setting)."""


def _check_rig_params(K: Tensor, dist: Tensor | None, R: Tensor, t: Tensor) -> int:
    """``C`` after checking the shapes of ``K (C, 3, 3)``, ``R (C, 3, 3)``, ``t (C, 3)`` and
    ``dist (C, 5)`` (:class:`CameraError`)."""
    if K.dim() != 3 or K.shape[-2:] != (3, 3):
        raise CameraError(f"K must have shape (C, 3, 3), got {tuple(K.shape)}")
    C = K.shape[0]
    if R.shape != (C, 3, 3):
        raise CameraError(f"R must have shape ({C}, 3, 3) to match K, got {tuple(R.shape)}")
    if t.shape != (C, 3):
        raise CameraError(f"t must have shape ({C}, 3) to match K, got {tuple(t.shape)}")
    if dist is not None and dist.shape != (C, 5):
        raise CameraError(f"dist must have shape ({C}, 5) (k1, k2, p1, p2, k3), got "
                          f"{tuple(dist.shape)}")
    return C


def intrinsics_matrix(fx: Tensor, fy: Tensor, cx: Tensor, cy: Tensor, skew: Tensor | None = None
                      ) -> Tensor:
    """Build pinhole intrinsics ``K`` from per-camera parameters.

    Args:
        fx, fy, cx, cy: focal lengths and principal point in pixels, each ``(*)``.
        skew: optional skew ``K[0, 1]`` in pixels, ``(*)`` (Bouguet stores ``alpha_c * fx``'s
            factor; pass the pixel value).

    Returns:
        ``K`` of shape ``(*, 3, 3)``.

    Example:
        >>> intrinsics_matrix(torch.tensor([500.]), torch.tensor([500.]),
        ...                   torch.tensor([160.]), torch.tensor([120.])).shape
        torch.Size([1, 3, 3])
    """
    fx, fy, cx, cy = torch.broadcast_tensors(fx, fy, cx, cy)
    zero = torch.zeros_like(fx)
    s = zero if skew is None else skew.expand_as(fx)
    one = torch.ones_like(fx)
    rows = [torch.stack([fx, s, cx], -1), torch.stack([zero, fy, cy], -1),
            torch.stack([zero, zero, one], -1)]
    return torch.stack(rows, -2)


def world_to_camera(points: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Transform world points into every camera frame: ``x_cam = R x + t``.

    Args:
        points: ``(*, N, 3)`` world points.
        R: ``(C, 3, 3)`` world-to-camera rotations.
        t: ``(C, 3)`` world-to-camera translations.

    Returns:
        ``(*, C, N, 3)`` points in each camera frame.

    Example:
        >>> world_to_camera(torch.zeros(7, 3), torch.eye(3)[None], torch.ones(1, 3)).shape
        torch.Size([1, 7, 3])
    """
    _check_last("points", points, (3,))
    # one matmul: (*, N, 3) x (C, 3, 3) -> (*, C, N, 3) (made contiguous: later reductions over
    # the last dim of a permuted layout are ~10x slower)
    return (torch.einsum("cij,...nj->...cni", R, points) + t[:, None, :]).contiguous()


def camera_centers(R: Tensor, t: Tensor) -> Tensor:
    """Optical centres in world coordinates, ``c = −Rᵀ t``.

    Args:
        R: ``(*, 3, 3)`` world-to-camera rotations.
        t: ``(*, 3)`` world-to-camera translations.

    Returns:
        ``(*, 3)`` camera centres in world units.
    """
    return -(R.transpose(-1, -2) @ t.unsqueeze(-1)).squeeze(-1)


def distort_normalized(xy: Tensor, dist: Tensor) -> Tensor:
    """Closed-form Brown–Conrady distortion of normalised image points (OpenCV model).

    ``x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)``,
    ``y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y``.

    Args:
        xy: ``(*, N, 2)`` points on the ``z = 1`` plane.
        dist: ``(*, 5)`` coefficients ``(k1, k2, p1, p2, k3)`` broadcastable to ``xy[..., 0, :]``.

    Returns:
        ``(*, N, 2)`` distorted normalised points. Used as the reference for kornia in the tests and
        for differentiable projection where kornia's pixel round trip is not wanted.
    """
    _check_last("xy", xy, (2,))
    _check_last("dist", dist, (5,))
    k1, k2, p1, p2, k3 = (dist[..., i, None] for i in range(5))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], -1)


def max_monotonic_radius(dist: Tensor, r_max: float = 3.0, steps: int = 3001) -> Tensor:
    """Largest normalised radius up to which the radial distortion ``r·(1+k1r²+k2r⁴+k3r⁶)`` grows.

    Beyond it a polynomial lens model folds back: a point far outside the field of view can be
    "distorted" into the image. :func:`project_points` marks such points invisible.

    Args:
        dist: ``(C, 5)`` distortion coefficients.
        r_max: search limit (returned where the model is monotonic on the whole range).
        steps: grid resolution of the search.

    Returns:
        ``(C,)`` radius on the normalised plane.
    """
    r = torch.linspace(0, r_max, steps, dtype=dist.dtype, device=dist.device)
    r2 = r * r
    k1, k2, k3 = dist[:, 0:1], dist[:, 1:2], dist[:, 4:5]
    deriv = 1 + 3 * k1 * r2 + 5 * k2 * r2**2 + 7 * k3 * r2**3  # (C, steps)
    bad = deriv <= 0
    first = torch.where(bad.any(-1), bad.float().argmax(-1), torch.full_like(bad[:, 0], steps - 1,
                                                                              dtype=torch.long))
    return r[first]


def project_points(points: Tensor, K: Tensor, R: Tensor, t: Tensor, dist: Tensor | None = None,
                   image_size: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Project world points into ``C`` cameras.

    Args:
        points: ``(*, N, 3)`` world points.
        K: ``(C, 3, 3)`` intrinsics.
        R: ``(C, 3, 3)`` world-to-camera rotations.
        t: ``(C, 3)`` world-to-camera translations (world units).
        dist: optional ``(C, 5)`` distortion ``(k1, k2, p1, p2, k3)``; ``None`` = ideal pinhole.
        image_size: optional ``(C, 2)`` as (width, height) in pixels; used for visibility.

    Returns:
        ``pixels (*, C, N, 2)`` (u, v), ``depth (*, C, N)`` (camera z, world units) and
        ``visible (*, C, N)`` bool: in front of the camera, inside the distortion model's
        monotonic region and (if ``image_size`` is given) inside ``[-0.5, W-0.5) × [-0.5, H-0.5)``.
        Points behind the camera still get finite pixels (depth clamped), flagged invisible;
        with lens distortion, points beyond :func:`max_monotonic_radius` are distorted from
        that radius along their direction (finite, flagged invisible).
        Differentiable w.r.t. ``points`` (and the camera parameters).

    Example:
        >>> K = torch.tensor([[[500., 0, 160], [0, 500, 120], [0, 0, 1]]])
        >>> pix, z, vis = project_points(torch.rand(4, 10, 3), K, torch.eye(3)[None],
        ...                              torch.tensor([[0., 0, 3]]))
        >>> pix.shape, vis.shape
        (torch.Size([4, 1, 10, 2]), torch.Size([4, 1, 10]))
    """
    _check_last("points", points, (3,))
    C = _check_rig_params(K, dist, R, t)
    distorted = dist is not None and bool((dist != 0).any())
    if not distorted:
        # pinhole fast path: one (K R | K t) transform gives (z u, z v, z) directly
        Kp = _pinhole(K)
        ph = world_to_camera(points, Kp @ R, (Kp @ t[..., None])[..., 0])  # (*, C, N, 3)
        depth = ph[..., 2]
        pixels = ph[..., :2] / depth.clamp_min(_DEPTH_EPS).unsqueeze(-1)
        return pixels, depth, _visible(pixels[..., 0], pixels[..., 1], depth, image_size, C)
    pc = world_to_camera(points, R, t)  # (*, C, N, 3)
    depth = pc[..., 2]
    z = depth.clamp_min(_DEPTH_EPS)
    xy = pc[..., :2] / z.unsqueeze(-1)
    visible = depth > _DEPTH_EPS
    if distorted:
        rmax = max_monotonic_radius(dist)  # (C,)
        r2 = (xy * xy).sum(-1)
        visible = visible & (r2 < (rmax * rmax)[:, None])
        # beyond the monotonic radius (and behind the camera) the polynomial overflows: such a
        # point is distorted from the radius limit along its direction (finite pixels, finite
        # gradients; it is flagged invisible)
        shrink = (rmax[:, None] / r2.clamp_min(1e-30).sqrt()).clamp(max=1.0)
        xy = xy * shrink.unsqueeze(-1)
        # kornia works on pixels with per-camera K: bring C to the front
        lead = xy.shape[:-3]
        n = xy.shape[-2]
        xy_c = xy.reshape(-1, C, n, 2).transpose(0, 1).reshape(C, -1, 2)
        ones = torch.ones_like(xy_c[..., :1])
        Kp = _pinhole(K)
        pix_u = torch.einsum("cij,cmj->cmi", Kp, torch.cat([xy_c, ones], -1))[..., :2]
        pix_c = _kornia_distort(pix_u, Kp, dist)
        pixels = pix_c.reshape(C, -1, n, 2).transpose(0, 1).reshape(*lead, C, n, 2)
    else:
        fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
        s, cx, cy = K[:, 0, 1, None], K[:, 0, 2, None], K[:, 1, 2, None]
        u = fx * xy[..., 0] + s * xy[..., 1] + cx
        v = fy * xy[..., 1] + cy
        pixels = torch.stack([u, v], -1)
    return pixels, depth, visible & _visible(pixels[..., 0], pixels[..., 1], depth, image_size, C)


def _pinhole(K: Tensor) -> Tensor:
    """``K`` reduced to the pinhole model's five parameters (fx, skew, cx / fy, cy) with the third
    row ``(0, 0, 1)``: the entries every projection path reads. ``K (R x + t)`` then has the
    depth as its z, and gradients never reach entries the model ignores (``K[1, 0]``, the third
    row), whichever path runs."""
    unit = K.new_tensor([0.0, 0.0, 1.0]).expand(K.shape[0], 1, 3)
    return torch.cat([K[:, :2].triu(), unit], 1)


def _visible(u: Tensor, v: Tensor, depth: Tensor, image_size: Tensor | None, C: int) -> Tensor:
    """In front of the camera and (with ``image_size``) inside ``[-0.5, W-0.5) x [-0.5, H-0.5)``;
    ``u, v, depth (*, C, N)``."""
    visible = depth > _DEPTH_EPS
    if image_size is not None:
        if image_size.shape != (C, 2):
            raise ValueError(f"image_size must have shape ({C}, 2) (width, height), got "
                             f"{tuple(image_size.shape)}")
        w = image_size[:, 0, None].to(u.dtype)
        h = image_size[:, 1, None].to(u.dtype)
        visible = visible & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
    return visible


def project_points_planar(points: Tensor, K: Tensor, R: Tensor, t: Tensor,
                          dist: Tensor | None = None, image_size: Tensor | None = None,
                          visibility: bool = True, distorted: bool | None = None
                          ) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """:func:`project_points` of a flat list ``points (M, 3)``, returned as planes.

    Returns ``u, v, depth, visible``, each ``(C, M)``: the layout batched likelihoods reduce
    over (views outermost, contiguous points). For a pinhole rig it is one matrix product
    ``(K R | K t)`` followed by the perspective division; with distortion, one product
    ``(R | t)``, the division and the lens model on the planes (:func:`_distort_planar`, the
    pixels of :func:`project_points` to the bit when the skew is 0, also beyond the lens
    model's monotonic radius). ``visibility=False`` skips
    the visibility test (``visible`` is then None) for callers that handle points behind the
    camera or outside the image themselves. ``distorted``: whether ``dist`` has a non-zero
    coefficient, when the caller knows (None: read from ``dist``, a host read that would split
    a compiled graph).
    """
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"points: expected shape (M, 3), got {tuple(points.shape)}")
    C = _check_rig_params(K, dist, R, t)
    Kp = _pinhole(K)
    if distorted is None:
        distorted = dist is not None and bool((dist != 0).any())
    if distorted:
        # world_to_camera's product and sum, then the perspective division, as planes
        pc = (R.reshape(3 * C, 3) @ points.T + t.reshape(3 * C, 1)).view(C, 3, -1)
        depth = pc[:, 2]
        z = depth.clamp_min(_DEPTH_EPS)
        x, y = pc[:, 0] / z, pc[:, 1] / z
        # beyond the lens model's monotonic radius, distorted from that radius along the
        # point's direction, as in project_points (a factor of exactly 1 inside it)
        rmax = max_monotonic_radius(dist)[:, None]  # (C, 1)
        r2 = x * x + y * y
        shrink = (rmax / r2.clamp_min(1e-30).sqrt()).clamp(max=1.0)
        u, v = _distort_planar(x * shrink, y * shrink, Kp, dist)
        if not visibility:
            return u, v, depth, None
        inside = r2 < rmax * rmax
        return u, v, depth, inside & _visible(u, v, depth, image_size, C)
    KR = (Kp @ R).reshape(3 * C, 3)
    Kt = (Kp @ t[..., None]).reshape(3 * C, 1)
    h = torch.addmm(Kt, KR, points.T).view(C, 3, -1)
    depth = h[:, 2]
    z = depth.clamp_min(_DEPTH_EPS)
    u, v = h[:, 0] / z, h[:, 1] / z
    return u, v, depth, _visible(u, v, depth, image_size, C) if visibility else None


def _distort_planar(x: Tensor, y: Tensor, Kp: Tensor, dist: Tensor) -> tuple[Tensor, Tensor]:
    """Distorted pixels ``u, v (C, M)`` of normalised points ``x, y (C, M)`` for pinhole
    intrinsics ``Kp (C, 3, 3)`` and ``dist (C, 5)``.

    The operations and their order are those of :func:`project_points`' path (the pixel of
    the undistorted point, back to the normalised plane, the Brown–Conrady polynomial, to
    pixels), written on planes instead of ``(C, M, 2)`` stacks, so both paths give the same
    pixels to the bit (for a skew of 0; with a skew the first step may round differently).
    """
    fx, s, cx = Kp[:, 0, 0, None], Kp[:, 0, 1, None], Kp[:, 0, 2, None]
    fy, cy = Kp[:, 1, 1, None], Kp[:, 1, 2, None]
    x = (fx * x + s * y + cx - cx) / fx
    y = (fy * y + cy - cy) / fy
    k1, k2, p1, p2, k3 = (dist[:, i, None] for i in range(5))
    r2 = x * x + y * y
    r4 = r2 * r2
    radial = 1 + k1 * r2 + k2 * r4 + k3 * (r4 * r2)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return fx * xd + cx, fy * yd + cy


def backproject_pixels(pixels: Tensor, K: Tensor, R: Tensor, t: Tensor, dist: Tensor | None = None,
                       num_iters: int = 20) -> tuple[Tensor, Tensor]:
    """Rays through pixels: origins at the camera centres, unit directions in world coordinates.

    Args:
        pixels: ``(*, C, N, 2)`` (u, v) pixel coordinates, one set per camera.
        K, R, t, dist: as in :func:`project_points`.
        num_iters: fixed-point iterations of the undistortion (kornia).

    Returns:
        ``origins (*, C, N, 3)`` and unit ``directions (*, C, N, 3)``; ``origin + s·direction``
        with ``s > 0`` projects back onto the pixel.

    Example:
        >>> K = torch.tensor([[[500., 0, 160], [0, 500, 120], [0, 0, 1]]])
        >>> o, d = backproject_pixels(torch.rand(1, 5, 2), K, torch.eye(3)[None], torch.zeros(1, 3))
        >>> d.shape
        torch.Size([1, 5, 3])
    """
    _check_last("pixels", pixels, (2,))
    C = _check_rig_params(K, dist, R, t)
    if pixels.dim() < 3 or pixels.shape[-3] != C:
        raise ValueError(f"pixels must have shape (*, {C}, N, 2) (one set per camera), got "
                         f"{tuple(pixels.shape)}")
    lead = pixels.shape[:-3]
    n = pixels.shape[-2]
    pc = pixels.reshape(-1, C, n, 2).transpose(0, 1).reshape(C, -1, 2)
    if dist is not None and bool((dist != 0).any()):
        pc = _kornia_undistort(pc, K, dist, num_iters=num_iters)
    ones = torch.ones_like(pc[..., :1])
    xyz = torch.einsum("cij,cmj->cmi", torch.linalg.inv(K), torch.cat([pc, ones], -1))
    d_world = torch.einsum("cji,cmj->cmi", R, xyz)  # R^T @ xyz
    d_world = d_world / d_world.norm(dim=-1, keepdim=True)
    directions = d_world.reshape(C, -1, n, 3).transpose(0, 1).reshape(*lead, C, n, 3)
    origins = camera_centers(R, t)[:, None, :].expand(C, n, 3)
    origins = origins.expand(*lead, C, n, 3)
    return origins, directions


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """World-to-camera ``(R, t)`` of a camera at ``eye`` looking at ``target`` (OpenCV axes).

    The camera's +z points to the target, +x to the image right, +y down (so world ``up``
    appears upwards in the image).

    Args:
        eye: ``(*, 3)`` camera centres.
        target: ``(*, 3)`` points looked at.
        up: ``(3,)`` or ``(*, 3)`` world up direction; default ``(0, 0, 1)`` (Z-up world).

    Returns:
        ``R (*, 3, 3)`` and ``t (*, 3)`` with ``x_cam = R x + t``.

    Raises:
        ValueError: if ``eye == target`` or the viewing direction is parallel to ``up``.

    Example:
        >>> R, t = look_at(torch.tensor([0., -4, 2.5]), torch.tensor([0., 0, 1]))
        >>> R.shape, t.shape
        (torch.Size([3, 3]), torch.Size([3]))
    """
    _check_last("eye", eye, (3,))
    _check_last("target", target, (3,))
    if up is None:
        up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype, device=eye.device)
    eye, target = torch.broadcast_tensors(eye, target)
    fwd = target - eye
    fn = fwd.norm(dim=-1, keepdim=True)
    if bool((fn < 1e-12).any()):
        raise ValueError("look_at: eye and target coincide")
    z = fwd / fn
    x = torch.linalg.cross(z, up.to(eye).expand_as(z))
    xn = x.norm(dim=-1, keepdim=True)
    if bool((xn < 1e-9).any()):
        raise ValueError("look_at: viewing direction is parallel to `up`; pass another `up`")
    x = x / xn
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z], -2)
    t = -(R @ eye.unsqueeze(-1)).squeeze(-1)
    return R, t
