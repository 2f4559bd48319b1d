"""``CameraRig``: a thin ``nn.Module`` holding C calibrated cameras; synthetic rig factories."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchmocap.cameras.projection import (
    CameraError,
    _check_rig_params,
    backproject_pixels,
    camera_centers,
    look_at,
    project_points,
    project_points_planar,
)

__all__ = ["CameraError", "CameraRig", "estimate_up_direction", "make_ceiling_rig",
           "make_ring_rig"]


def _check_image_size(image_size, C: int | None = None, name: str = "image_size") -> Tensor:
    """``image_size`` as int64 ``(C, 2)`` (or ``(2,)`` when ``C`` is None): positive whole
    numbers of pixels; 320.5, 0, -240, NaN or inf are errors naming ``name``."""
    try:
        raw = torch.as_tensor(image_size)
    except (TypeError, ValueError, RuntimeError):
        raise CameraError(f"{name}: expected (width, height) in pixels, got {image_size!r}"
                          ) from None
    want = "(2,)" if C is None else f"({C}, 2) or (2,)"
    if raw.dtype == torch.bool or raw.is_complex():
        raise CameraError(f"{name}: expected {want} whole numbers of pixels, got {image_size!r}")
    if raw.shape == (2,) and C is not None:
        raw = raw.expand(C, 2)
    if raw.shape != ((2,) if C is None else (C, 2)):
        raise CameraError(f"{name}: expected shape {want} (width, height), got "
                          f"{tuple(raw.shape)}")
    f = raw.double()
    if not bool((torch.isfinite(f) & (f > 0) & (f == f.round())).all()):
        raise CameraError(f"{name}: expected positive whole numbers of pixels (width, height), "
                          f"got {raw.tolist()}")
    return f.long().clone()


def _check_focal(K: Tensor) -> None:
    """Pinhole intrinsics: ``fx, fy > 0`` and the third row ``(0, 0, 1)``, ``K[1, 0] = 0`` (the
    entries projection reads; anything else there would be silently ignored)."""
    fx, fy = K[:, 0, 0], K[:, 1, 1]
    bad = ~((fx > 0) & (fy > 0))
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        raise CameraError(f"K: focal lengths must be positive; camera {i} has fx = "
                          f"{float(fx[i]):g}, fy = {float(fy[i]):g}")
    form = torch.stack([K[:, 1, 0], K[:, 2, 0], K[:, 2, 1], K[:, 2, 2] - 1], -1)
    off = form.abs().amax(-1) > 1e-9 * torch.maximum(fx, fy).clamp_min(1)
    if bool(off.any()):
        i = int(off.nonzero()[0])
        raise CameraError(f"K: expected pinhole intrinsics [[fx, s, cx], [0, fy, cy], "
                          f"[0, 0, 1]]; camera {i} has K = {K[i].tolist()}")


def _check_number(value, name: str, what: str, ok) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not \
            math.isfinite(value) or not ok(value):
        raise CameraError(f"{name}: expected {what}, got {value!r}")
    return float(value)


def _check_point(value, name: str) -> Tensor:
    try:
        p = torch.as_tensor(list(value), dtype=torch.float64)
    except (TypeError, ValueError):
        raise CameraError(f"{name}: expected a 3D point (x, y, z) in metres, got {value!r}"
                          ) from None
    if p.shape != (3,) or not bool(torch.isfinite(p).all()):
        raise CameraError(f"{name}: expected a finite 3D point (x, y, z) in metres, got "
                          f"{value!r}")
    return p


def _is_rotation(R: Tensor, tol: float) -> Tensor:
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    orth = (R @ R.transpose(-1, -2) - eye).abs().amax(dim=(-1, -2)) < tol
    return orth & ((torch.linalg.det(R) - 1).abs() < tol)


class CameraRig(nn.Module):
    """C pinhole cameras with Brown–Conrady distortion (OpenCV conventions).

    Buffers (move with ``.to(device/dtype)``): ``K (C, 3, 3)``, ``dist (C, 5)``
    (k1, k2, p1, p2, k3), ``R (C, 3, 3)`` world-to-camera rotation, ``t (C, 3)`` translation
    (``x_cam = R x + t``, world metres), ``image_size (C, 2)`` (width, height) as int64.

    Args:
        K: ``(C, 3, 3)`` pinhole intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with
            ``fx, fy > 0`` (checked: a zero or negative focal length is an error here, not a
            failed linear solve later).
        R: ``(C, 3, 3)`` rotations (checked orthonormal with det +1).
        t: ``(C, 3)`` translations.
        image_size: ``(C, 2)`` or ``(2,)`` (width, height), positive whole numbers of pixels.
        dist: ``(C, 5)`` distortion; default zeros.
        names: optional camera names.

    Example:
        >>> rig = make_ring_rig(4)
        >>> pix, depth, vis = rig.project(torch.zeros(7, 3))
        >>> pix.shape
        torch.Size([4, 7, 2])
    """

    K: Tensor
    dist: Tensor
    R: Tensor
    t: Tensor
    image_size: Tensor

    def __init__(self, K: Tensor, R: Tensor, t: Tensor, image_size: Tensor | Sequence[int],
                 dist: Tensor | None = None, names: Sequence[str] | None = None) -> None:
        super().__init__()
        K = torch.as_tensor(K)
        if not K.is_floating_point():
            K = K.double()
        R, t = torch.as_tensor(R, dtype=K.dtype), torch.as_tensor(t, dtype=K.dtype)
        C = _check_rig_params(K, None, R, t)
        dist = torch.zeros(C, 5, dtype=K.dtype) if dist is None else torch.as_tensor(
            dist, dtype=K.dtype)
        _check_rig_params(K, dist, R, t)
        size = _check_image_size(image_size, C)
        for name, x in (("K", K), ("R", R), ("t", t), ("dist", dist)):
            if not bool(torch.isfinite(x).all()):
                raise CameraError(f"{name} contains non-finite values")
        _check_focal(K)
        tol = 1e-4 if K.dtype == torch.float32 else 1e-6
        ok = _is_rotation(R, tol)
        if names is not None and len(names) != C:
            raise CameraError(f"names must have {C} entries, got {len(names)}")
        if not bool(ok.all()):
            bad = [i for i in range(C) if not bool(ok[i])]
            which = "R" if C == 1 else (f"R of camera(s) {[names[i] for i in bad]}"
                                        if names is not None else f"R of camera(s) {bad}")
            raise CameraError(f"{which} is not a rotation matrix (R Rᵀ ≠ I or det ≠ 1)")
        self.names = list(names) if names is not None else [f"cam{i}" for i in range(C)]
        self.register_buffer("K", K)
        self.register_buffer("dist", dist)
        self.register_buffer("R", R)
        self.register_buffer("t", t)
        self.register_buffer("image_size", size)

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]

    def __len__(self) -> int:
        return self.num_cameras

    @property
    def has_distortion(self) -> bool:
        return bool((self.dist != 0).any())

    def camera_centers(self) -> Tensor:
        """``(C, 3)`` optical centres in world coordinates."""
        return camera_centers(self.R, self.t)

    def optical_axes(self) -> Tensor:
        """``(C, 3)`` unit viewing directions (camera +z) in world coordinates."""
        return self.R[:, 2, :]

    def project(self, points: Tensor, distort: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """Project ``(*, N, 3)`` world points; see :func:`project_points`.

        Returns ``pixels (*, C, N, 2)``, ``depth (*, C, N)``, ``visible (*, C, N)`` (in front and
        inside the image). ``distort=False`` ignores the lens distortion.
        """
        return project_points(points, self.K.to(points.dtype), self.R.to(points.dtype),
                              self.t.to(points.dtype),
                              self.dist.to(points.dtype) if distort else None, self.image_size)

    def project_planar(self, points: Tensor, distort: bool = True, visibility: bool = True,
                       distorted: bool | None = None
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """``u, v, depth, visible`` planes ``(C, M)`` of world points ``(M, 3)``; see
        :func:`project_points_planar` (``visibility=False``: ``visible`` is None;
        ``distorted``: :attr:`has_distortion` when the caller has read it already)."""
        dt = points.dtype
        if not distort:
            distorted = False
        return project_points_planar(points, self.K.to(dt), self.R.to(dt), self.t.to(dt),
                                     self.dist.to(dt) if distort else None, self.image_size,
                                     visibility, distorted)

    def forward(self, points: Tensor) -> Tensor:
        """Pixels ``(*, C, N, 2)`` of ``(*, N, 3)`` world points (with distortion)."""
        return self.project(points)[0]

    def backproject(self, pixels: Tensor, undistort: bool = True, num_iters: int = 20
                    ) -> tuple[Tensor, Tensor]:
        """Rays ``(origins, unit directions)`` ``(*, C, N, 3)`` of ``(*, C, N, 2)`` pixels."""
        dt = pixels.dtype
        return backproject_pixels(pixels, self.K.to(dt), self.R.to(dt), self.t.to(dt),
                                  self.dist.to(dt) if undistort else None, num_iters)

    def subset(self, indices: Sequence[int]) -> CameraRig:
        """A rig with the cameras at ``indices`` (in that order)."""
        idx = torch.as_tensor(list(indices), dtype=torch.long)
        return CameraRig(self.K[idx], self.R[idx], self.t[idx], self.image_size[idx],
                         self.dist[idx], [self.names[i] for i in idx.tolist()])

    def scaled_images(self, factor: float) -> CameraRig:
        """The same cameras with images resized by ``factor`` (intrinsics scaled, centres kept)."""
        K = self.K.clone()
        K[:, :2, :] *= factor
        # pixel-centre convention: u' + 0.5 = factor (u + 0.5)
        K[:, 0, 2] += 0.5 * factor - 0.5
        K[:, 1, 2] += 0.5 * factor - 0.5
        size = torch.round(self.image_size.double() * factor).long()
        return CameraRig(K, self.R, self.t, size, self.dist, self.names)

    def extra_repr(self) -> str:
        return f"num_cameras={self.num_cameras}, distortion={self.has_distortion}"


def _focal_from_fov(width: float, fov_deg: float) -> float:
    _check_number(fov_deg, "fov_deg", "a field of view in (0, 180) degrees",
                  lambda v: 0 < v < 180)
    return 0.5 * width / math.tan(math.radians(fov_deg) / 2)


def _check_num(num) -> int:
    if isinstance(num, bool) or not isinstance(num, int) or num < 1:
        raise CameraError(f"num: expected an integer number of cameras ≥ 1, got {num!r}")
    return num


def _rig_from_eyes(eyes: Tensor, targets: Tensor, image_size: Sequence[int], fov_deg: float,
                   up: Tensor, names: list[str]) -> CameraRig:
    w, h = (int(v) for v in _check_image_size(image_size).tolist())
    f = _focal_from_fov(w, fov_deg)
    C = eyes.shape[0]
    K = torch.tensor([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]],
                     dtype=torch.float64).expand(C, 3, 3).clone()
    R, t = look_at(eyes, targets, up)
    return CameraRig(K, R, t, (w, h), None, names)


def make_ring_rig(num: int = 4, radius: float = 4.0, height: float = 2.5,
                  target: Sequence[float] = (0.0, 0.0, 1.0),
                  image_size: Sequence[int] = (320, 240), fov_deg: float = 60.0,
                  start_angle_deg: float = -90.0) -> CameraRig:
    """``num`` cameras evenly spaced on a horizontal ring, all looking at ``target`` (Z-up world).

    Args:
        num: number of cameras (≥ 1).
        radius: ring radius in metres (distance from the vertical axis through ``target``).
        height: camera height in metres.
        target: point all cameras look at, metres.
        image_size: (width, height) in pixels.
        fov_deg: horizontal field of view in degrees (sets ``fx = fy``).
        start_angle_deg: azimuth of the first camera around ``target`` (−90° = on the −y side,
            seeing the front of a human31 skeleton at rest, which faces −y).

    Returns:
        a distortion-free :class:`CameraRig` in float64.

    Example:
        >>> make_ring_rig(4, image_size=(640, 480)).K[0, 0, 0].round()
        tensor(554., dtype=torch.float64)
    """
    _check_num(num)
    _check_number(radius, "radius", "a positive finite distance (m)", lambda v: v > 0)
    _check_number(height, "height", "a finite height (m)", lambda v: True)
    _check_number(start_angle_deg, "start_angle_deg", "a finite angle (deg)", lambda v: True)
    _check_image_size(image_size)
    _focal_from_fov(1.0, fov_deg)
    tgt = _check_point(target, "target")
    ang = torch.deg2rad(torch.tensor(start_angle_deg, dtype=torch.float64)) + \
        torch.arange(num, dtype=torch.float64) * (2 * math.pi / num)
    eyes = torch.stack([tgt[0] + radius * torch.cos(ang), tgt[1] + radius * torch.sin(ang),
                        torch.full_like(ang, height)], -1)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    return _rig_from_eyes(eyes, tgt.expand(num, 3), image_size, fov_deg, up,
                          [f"ring{i}" for i in range(num)])


def make_ceiling_rig(num: int = 4, half_width: float = 2.0, height: float = 3.0,
                     target: Sequence[float] = (0.0, 0.0, 0.9),
                     image_size: Sequence[int] = (320, 240), fov_deg: float = 70.0) -> CameraRig:
    """``num`` cameras in the upper corners of a square room looking down at ``target``.

    Cameras sit on a circle of radius ``half_width·√2`` (the corners of a square of side
    ``2·half_width`` when ``num = 4``) at ``height`` metres, like the bodytrack office rig.

    Returns:
        a distortion-free :class:`CameraRig` in float64.
    """
    _check_num(num)
    _check_number(half_width, "half_width", "a positive finite distance (m)", lambda v: v > 0)
    _check_number(height, "height", "a finite height (m)", lambda v: True)
    _check_image_size(image_size)
    _focal_from_fov(1.0, fov_deg)
    tgt = _check_point(target, "target")
    ang = math.pi / 4 + torch.arange(num, dtype=torch.float64) * (2 * math.pi / num)
    r = half_width * math.sqrt(2)
    eyes = torch.stack([tgt[0] + r * torch.cos(ang), tgt[1] + r * torch.sin(ang),
                        torch.full_like(ang, height)], -1)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    return _rig_from_eyes(eyes, tgt.expand(num, 3), image_size, fov_deg, up,
                          [f"ceiling{i}" for i in range(num)])


def estimate_up_direction(rig: CameraRig) -> Tensor:
    """World "up" of a calibration, from where its cameras are and where they look.

    Assumes the usual capture set-up: cameras mounted at roughly equal heights around the
    subject (so their centres span a horizontal plane) and tilted down. With ≥ 3 cameras the
    up direction is the normal of the least-squares plane through the camera centres, signed so
    that the mean optical axis points down; with fewer it is minus the mean optical axis's
    component orthogonal to the baseline (a coarse guess).

    For the bodytrack office calibration this gives (0.003, −0.006, 1.000) (0.4° from +z): the
    world is Z-up in millimetres with the floor at z ≈ 0 and the cameras at 2.53–2.58 m.

    Returns:
        ``(3,)`` unit vector (float64).
    """
    c = rig.camera_centers().double()
    axes = rig.optical_axes().double()
    mean_axis = axes.mean(0)
    if rig.num_cameras >= 3:
        centred = c - c.mean(0)
        _, S, Vh = torch.linalg.svd(centred)
        n = Vh[-1]
        if float(S[1]) < 1e-9:
            raise CameraError("camera centres are collinear: the up direction is ambiguous")
    else:
        n = -mean_axis
        if rig.num_cameras == 2:
            base = (c[1] - c[0]) / (c[1] - c[0]).norm().clamp_min(1e-12)
            n = n - (n @ base) * base
    n = n / n.norm()
    return -n if float(n @ mean_axis) > 0 else n
