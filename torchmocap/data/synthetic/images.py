"""Colour images for an appearance term: per-part albedo, Lambertian shading, a textured
background (checkered floor and a striped cylindrical wall seen through each camera), floor
shadows, and a global illumination change over time.

Images are ``(H, W, 3)`` float in [0, 1] while composed and ``uint8`` at the end.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "PART_COLOURS",
    "background_images",
    "illumination_gain",
    "part_albedo",
    "shade_body",
    "to_uint8",
]

#: albedo (linear RGB in [0, 1]) of each human31 bone frame: shirt, trousers, skin, shoes
PART_COLOURS: dict[str, tuple[float, float, float]] = {
    "pelvis": (0.20, 0.22, 0.45),
    "spine": (0.75, 0.25, 0.20),
    "neck": (0.85, 0.65, 0.52),
    "head": (0.85, 0.65, 0.52),
    "l_shoulder": (0.80, 0.45, 0.15),
    "r_shoulder": (0.70, 0.20, 0.30),
    "l_elbow": (0.82, 0.62, 0.50),
    "r_elbow": (0.80, 0.60, 0.48),
    "l_wrist": (0.82, 0.62, 0.50),
    "r_wrist": (0.80, 0.60, 0.48),
    "l_hip": (0.22, 0.28, 0.55),
    "r_hip": (0.18, 0.24, 0.50),
    "l_knee": (0.15, 0.35, 0.45),
    "r_knee": (0.12, 0.30, 0.40),
    "l_ankle": (0.12, 0.10, 0.09),
    "r_ankle": (0.14, 0.12, 0.10),
}
_DEFAULT_COLOUR = (0.5, 0.5, 0.5)

_WALL_RADIUS = 8.0
_TILE = 0.5


def part_albedo(part_names: list[str], face_part: Tensor) -> Tensor:
    """Albedo ``(F, 3)`` of each face from its part index into ``part_names``."""
    table = torch.tensor([PART_COLOURS.get(n, _DEFAULT_COLOUR) for n in part_names],
                         dtype=torch.float32)
    return table[face_part.cpu()].to(face_part.device)


def _hash_noise(i: Tensor, j: Tensor, seed: int) -> Tensor:
    """Deterministic value noise in [0, 1) on an integer lattice."""
    h = (i * 73856093) ^ (j * 19349663) ^ (seed * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF).double() / 65536.0


def background_images(rig, light_direction: Tensor, ambient: float, seed: int = 0) -> Tensor:
    """Background ``(C, H, W, 3)`` float of every camera: floor and a surrounding wall.

    The floor ``z = 0`` carries 0.5 m tiles with per-tile value noise (Lambertian lit); beyond
    8 m from the origin, or for rays above the horizon, a cylindrical wall shows vertical stripes
    and a brick-like band pattern. Rays come from :meth:`CameraRig.backproject` so the texture is
    consistent across views.
    """
    W, H = int(rig.image_size[0, 0]), int(rig.image_size[0, 1])
    C = rig.num_cameras
    dt = torch.float64
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dt), torch.arange(W, dtype=dt), indexing="ij")
    pix = torch.stack([xs, ys], -1).reshape(1, -1, 2).expand(C, -1, 2)
    from torchmocap.cameras import backproject_pixels

    o, d = backproject_pixels(pix, rig.K.to(dt), rig.R.to(dt), rig.t.to(dt), rig.dist.to(dt))
    # floor hit
    s_floor = torch.where(d[..., 2] < -1e-9, -o[..., 2] / d[..., 2].clamp(max=-1e-9),
                          torch.full_like(d[..., 2], math.inf))
    p_floor = o + s_floor[..., None] * d
    on_floor = torch.isfinite(s_floor) & (p_floor[..., :2].norm(dim=-1) < _WALL_RADIUS)
    # wall hit (cylinder of radius R around the z axis)
    a = (d[..., :2] ** 2).sum(-1).clamp_min(1e-12)
    b = 2 * (o[..., :2] * d[..., :2]).sum(-1)
    c = (o[..., :2] ** 2).sum(-1) - _WALL_RADIUS**2
    s_wall = (-b + torch.sqrt((b * b - 4 * a * c).clamp_min(0))) / (2 * a)
    p_wall = o + s_wall[..., None] * d
    # floor texture: tiles with value noise, grout lines
    fx, fy = p_floor[..., 0] / _TILE, p_floor[..., 1] / _TILE
    ti, tj = torch.floor(fx).long(), torch.floor(fy).long()
    checker = ((ti + tj) % 2).double()
    tone = 0.45 + 0.12 * checker + 0.10 * _hash_noise(ti, tj, seed)
    grout = ((fx - ti) < 0.04) | ((fy - tj) < 0.04)
    tone = torch.where(grout, tone * 0.6, tone)
    floor_rgb = tone[..., None] * torch.tensor([0.80, 0.85, 0.70], dtype=dt)
    ld = torch.nn.functional.normalize(light_direction.to(dt), dim=0)
    floor_light = ambient + (1 - ambient) * max(0.0, float(-ld[2]))
    floor_rgb = floor_rgb * floor_light
    # wall texture: stripes in azimuth, bands in height
    az = torch.atan2(p_wall[..., 1], p_wall[..., 0])
    si = torch.floor(az / (2 * math.pi) * 48).long()
    hz = torch.floor(p_wall[..., 2] / 0.4).long()
    wall_tone = 0.50 + 0.15 * ((si % 2).double()) + 0.15 * _hash_noise(si, hz, seed + 1)
    wall_rgb = wall_tone[..., None] * torch.tensor([0.65, 0.70, 0.85], dtype=dt)
    sky = p_wall[..., 2] > 4.0
    wall_rgb = torch.where(sky[..., None], torch.tensor([0.75, 0.85, 0.95], dtype=dt), wall_rgb)
    rgb = torch.where(on_floor[..., None], floor_rgb, wall_rgb * (0.5 + 0.5 * ambient + 0.2))
    return rgb.clamp(0, 1).reshape(C, H, W, 3).float()


def illumination_gain(T: int, fps: float, amplitude: float, period_s: float,
                      generator: torch.Generator) -> Tensor:
    """``(T,)`` global brightness factor ``1 + a·sin(2π t / P + φ)`` with a seeded phase."""
    phase = float(torch.rand((), generator=generator, dtype=torch.float64)) * 2 * math.pi
    t = torch.arange(T, dtype=torch.float64) / fps
    return (1 + amplitude * torch.sin(2 * math.pi * t / period_s + phase)).float()


def shade_body(normals: Tensor, albedo: Tensor, view_dirs: Tensor, light_direction: Tensor,
               ambient: float) -> Tensor:
    """Lambertian colour ``(N, 3)`` of body points.

    Args:
        normals: ``(N, 3)`` unit surface normals (flipped to face the camera).
        albedo: ``(N, 3)``.
        view_dirs: ``(N, 3)`` directions from the camera to the points.
        light_direction: ``(3,)`` direction the light travels.
        ambient: ambient fraction.
    """
    n = torch.where(((normals * view_dirs).sum(-1, keepdim=True) > 0), -normals, normals)
    ld = torch.nn.functional.normalize(light_direction.to(normals), dim=0)
    lam = (n * -ld).sum(-1).clamp_min(0)
    return albedo * (ambient + (1 - ambient) * lam)[:, None]


def to_uint8(images: Tensor, noise: float, generator: torch.Generator) -> Tensor:
    """Add Gaussian pixel noise (0–255 scale) and quantise to ``uint8``."""
    x = images * 255.0
    if noise > 0:
        x = x + noise * torch.randn(x.shape, generator=generator, dtype=torch.float32).to(x)
    return x.round().clamp(0, 255).to(torch.uint8)
