"""Silhouette likelihood of the fitted Anny body's surface: posed surface points against the
masks, instead of the capsules' projected stadiums.

The body's skin is summarised by ``N`` of its vertices (farthest-point samples of the rest
skin, :func:`surface_samples`); every particle poses them by linear blend skinning
(:meth:`~torchmocap.body.ParametricBody.pose_surface`, the rest points and alignments computed
once per phenotype). The energy is the distance version of :mod:`torchmocap.likelihoods.
silhouette` (a symmetric robust chamfer) with surface points in place of capsule samples:

- model -> image: the mean over the points of ``rho(d)``, ``d`` the distance (pixels, the masks'
  distance transform, bilinear) of the projected point to the foreground — every point of a
  body's surface projects inside its silhouette, whatever occludes it;
- image -> model: over ``G`` foreground samples per view, ``rho(relu(d - f r / z))``, ``d`` the
  distance to the nearest projected point and ``f r / z`` the pixel footprint of a point
  (``r`` half the samples' covering radius on the skin: a foreground pixel inside the body is
  within about that of a sample);

``rho(d) = d^2 / (d^2 + s^2)``, the mean over usable views of the two halves' mean (1 without
any usable view). Batched over particles, differentiable in the points (the nearest point's
gradient in the image -> model half). Cost ``O(P C N G)``.

The term poses the phenotype that a body fit wrote on the runtime body
(:class:`~torchmocap.filters.AnnyBodyFit` sets ``body.surface_phenotype``), else its own
``phenotype`` (Anny's default body when None), driven by the tracking skeleton's offsets.
"""

from __future__ import annotations

import math

import torch

from torchmocap.likelihoods.base import Likelihood, blockwise, check_block
from torchmocap.likelihoods.silhouette import (
    SilhouetteObservation,
    _lookup_distance,
    _over_views,
    _robust,
    prepare_silhouettes,
)

__all__ = ["SurfaceSilhouetteLikelihood", "surface_samples", "surface_silhouette_energy"]


def surface_samples(points: torch.Tensor, num: int) -> tuple[torch.Tensor, float]:
    """Farthest-point samples of ``points (V, 3)``: indices ``(num,)`` (deterministic, from the
    point nearest the centroid) and the covering radius (metres: every point lies within it of
    a sample)."""
    if isinstance(num, bool) or not isinstance(num, int) or not 1 <= num <= points.shape[0]:
        raise ValueError(f"num: expected an int in [1, {points.shape[0]}], got {num!r}")
    p = points.detach().double()
    first = int((p - p.mean(0)).norm(dim=-1).argmin())
    idx = [first]
    d = (p - p[first]).norm(dim=-1)
    for _ in range(num - 1):
        i = int(d.argmax())
        idx.append(i)
        d = torch.minimum(d, (p - p[i]).norm(dim=-1))
    return torch.tensor(idx, dtype=torch.long), float(d.max())


def surface_silhouette_energy(points: torch.Tensor, rig, obs: SilhouetteObservation,
                              distance: float | torch.Tensor, footprint: float) -> torch.Tensor:
    """``(P,)`` robust chamfer of surface points ``(P, N, 3)`` against the masks (module
    docstring), in [0, 1]; 0 where every point projects onto the foreground and every
    foreground sample lies within a point's footprint (``footprint`` metres). ``distance``: the
    robust scale (pixels), a number or per view ``(C,)``; ``obs`` needs
    ``prepare_silhouettes(..., distance=True)``."""
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"points: expected shape (P, N, 3), got {tuple(points.shape)}")
    if obs.outside is None:
        raise ValueError("obs: the surface term needs prepare_silhouettes(..., distance=True)")
    P, N, _ = points.shape
    dt = points.dtype
    u, v, z, _ = rig.project_planar(points.reshape(P * N, 3), visibility=False)
    C = u.shape[0]
    u, v, z = u.view(C, P, N), v.view(C, P, N), z.view(C, P, N)
    s = distance if not isinstance(distance, torch.Tensor) else \
        distance.to(dt).view(C, 1, 1)
    m2i = _robust(_lookup_distance(obs.outside, u, v), s).mean(-1)  # (C, P)
    f = rig.K[:, 0, 0].to(dt).view(C, 1, 1)
    reach = f * footprint / z.clamp_min(1e-3)  # (C, P, N) pixels
    q = obs.fg_pixels.to(dt)  # (C, G, 2)
    du = q[:, :, None, None, 0] - u[:, None]  # (C, G, P, N)
    dv = q[:, :, None, None, 1] - v[:, None]
    d = ((du * du + dv * dv + 1e-12).sqrt() - reach[:, None]).amin(-1)  # (C, G, P)
    fv = obs.fg_valid.to(dt)[..., None]
    i2m = (_robust(torch.relu(d), s) * fv).sum(1) / fv.sum(1).clamp_min(1)  # (C, P)
    return _over_views(m2i, i2m, obs.view_valid)


class SurfaceSilhouetteLikelihood(Likelihood):
    """Silhouette energy of the Anny body's posed surface points (module docstring).

    Args:
        body: the runtime :class:`~torchmocap.body.CapsuleBody` (its skeleton is the tracking
            skeleton; a body fit's ``surface_phenotype`` on it is the phenotype posed).
        rig: the cameras of the masks.
        num_points: ``N`` surface points (farthest-point samples of the rest skin).
        fg_samples: ``G`` foreground pixels per view.
        distance: robust scale (pixels, at ``reference_width``).
        reference_width: the image width the pixel settings are given for (each view scales
            them by its width / ``reference_width``); None: raw pixels.
        phenotype: the phenotype posed without a body fit (``{name: value}``; None: Anny's
            default body).
        cache_dir: the Anny cache folder (read at the first energy).
        block: particles per block.
    """

    requires = ("silhouettes",)
    differentiable = True

    def __init__(self, body, rig, num_points: int = 400, fg_samples: int = 64,
                 distance: float = 1.0, reference_width: float | None = 320.0,
                 phenotype: dict | None = None, cache_dir: str | None = None,
                 block: int | None = 256) -> None:
        super().__init__()
        if isinstance(num_points, bool) or not isinstance(num_points, int) or num_points < 1:
            raise ValueError(f"num_points: expected an int >= 1, got {num_points!r}")
        if isinstance(fg_samples, bool) or not isinstance(fg_samples, int) or fg_samples < 1:
            raise ValueError(f"fg_samples: expected an int >= 1, got {fg_samples!r}")
        for name, x, none_ok in (("distance", distance, False),
                                 ("reference_width", reference_width, True)):
            if x is None and none_ok:
                continue
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) \
                    or x <= 0:
                raise ValueError(f"{name}: expected a finite number of pixels > 0, got {x!r}")
        if phenotype is not None and not hasattr(phenotype, "items"):
            raise ValueError(f"phenotype: expected a mapping of phenotype values or None, got "
                             f"{phenotype!r}")
        self.body, self.rig = body, rig
        self.num_points, self.fg_samples = num_points, fg_samples
        self.distance = float(distance)
        self.reference_width = None if reference_width is None else float(reference_width)
        self.phenotype = None if phenotype is None else dict(phenotype)
        self.cache_dir = cache_dir
        self.block = check_block(block)
        self._parametric = None
        self._surface = None  # (key, RestSurface, footprint)

    def _rest(self, dtype: torch.dtype):
        sk = self.body.skeleton
        if self._parametric is None:
            from torchmocap.body import ParametricBody

            self._parametric = ParametricBody(sk, cache_dir=self.cache_dir).to(
                sk.offsets.device)
        pb = self._parametric
        phen = getattr(self.body, "surface_phenotype", None)
        if phen is None:
            phen = pb.phenotype_tensor(self.phenotype)
        phen = phen.detach().to(dtype)
        off = sk.offsets.detach().to(dtype)
        key = (tuple(phen.tolist()), dtype, off.data_ptr(), float(off.abs().sum()))
        if self._surface is None or self._surface[0] != key:
            full = pb.rest_surface(phen, off, dtype=dtype)
            idx, cover = surface_samples(full.rest, self.num_points)
            rs = pb.rest_surface(phen, off, idx, dtype=dtype)
            self._surface = (key, rs, 0.5 * cover)
        return pb, self._surface[1], self._surface[2]

    def view_scale(self) -> torch.Tensor | float:
        if self.reference_width is None:
            return 1.0
        return self.rig.image_size[:, 0].to(self.body.radii.dtype) / self.reference_width

    def prepare(self, frame) -> SilhouetteObservation:
        view_valid = None
        if getattr(frame, "view_dropped", None) is not None:
            view_valid = ~frame.view_dropped.bool()
        return prepare_silhouettes(frame.silhouettes, self.fg_samples, blur=0.0,
                                   view_valid=view_valid, dtype=self.body.radii.dtype,
                                   distance=True)

    def evidence(self, observation: SilhouetteObservation) -> bool:
        return bool(observation.view_valid.any())

    def points(self, poses) -> torch.Tensor:
        """``(P, N, 3)`` the surface points posed by ``poses``."""
        pb, rs, _ = self._rest(poses.theta.dtype)
        return pb.pose_surface(rs, poses.kinematics)

    def energy(self, poses, observation: SilhouetteObservation) -> torch.Tensor:
        _, _, footprint = self._rest(poses.theta.dtype)
        return blockwise(surface_silhouette_energy, self.points(poses), self.block, self.rig,
                         observation, self.distance * self.view_scale(), footprint)

    def extra_repr(self) -> str:
        return (f"num_points={self.num_points}, fg_samples={self.fg_samples}, "
                f"distance={self.distance}")
