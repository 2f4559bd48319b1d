"""Reprojection residuals of 2D detections for refining cameras: robust, confidence-weighted,
with per-camera time offsets; the loss any objective (free 3D points, a skeleton's keypoints)
builds on.

* :func:`refinement_pixels`: pixels of world points in every camera (pinhole + Brown–Conrady,
  the model of :func:`~torchmocap.cameras.project_points`, always through the lens polynomial
  so derivatives in ``k1``, ``k2`` are right at zero distortion).
* :func:`interpolate_in_time`: a trajectory ``(T, K, 3)`` at fractional frame times, by
  Catmull–Rom cubic interpolation (C¹ in time: the derivative in a time offset is continuous
  across whole frames), extrapolated linearly past the first and last frames.
* :func:`reprojection_residuals`: detections minus projections ``(T, C, K, 2)``; a camera
  ``c`` with time offset ``δ_c`` sees at its frame ``t`` the subject at time ``t + δ_c``. The
  points are a tensor ``(T, K, 3)`` (interpolated in time when offsets are given) or any
  callable ``points(times (C, T)) -> (C, T, K, 3)`` (e.g. a skeleton's keypoints given poses
  interpolated at those times).
* :class:`RobustLoss`: Cauchy, Huber or squared loss of the pixel distance ``‖r‖`` of each
  detection, with a scale in pixels, a minimum confidence and confidence weights; its
  :meth:`~RobustLoss.weight` is the IRLS weight ``ρ'(‖r‖²)``.
* :func:`reprojection_loss` ``= ½ Σ w ρ(‖r‖²) / σ²`` and :func:`prior_loss`; the module
  :class:`RigRefinement` holds the refined parameters and returns their sum (for gradient-based
  refinement inside another objective).

Shapes: ``T`` frames, ``C`` cameras, ``K`` keypoints (points). Pixels are those of the rig's
images.

Example:
    >>> from torchmocap.cameras import make_ring_rig
    >>> rig = make_ring_rig(3).double()
    >>> X = torch.rand(5, 7, 3, dtype=torch.float64) * 0.5 + torch.tensor([0.0, 0.0, 1.0])
    >>> det = torch.cat([rig.project(X)[0] + 1.0,                        # (T, C, K, 2)
    ...                  torch.ones(5, 3, 7, 1, dtype=torch.float64)], -1)   # (T, C, K, 3)
    >>> r = reprojection_residuals(X, det, rig.K, rig.R, rig.t, rig.dist)
    >>> r.shape, round(float(r.abs().max()), 6)
    (torch.Size([5, 3, 7, 2]), 1.0)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from torchmocap.cameras.projection import distort_normalized
from torchmocap.cameras.rig import CameraRig
from torchmocap.cameras.rig_parameters import (
    DEFAULT_GROUPS,
    RefinementError,
    RigParametrization,
    apply_rig_parameters,
)
from torchmocap.cameras.rig_priors import RigPriors

__all__ = [
    "ROBUST_LOSSES",
    "RigRefinement",
    "RobustLoss",
    "interpolate_in_time",
    "interpolation_weights",
    "prior_loss",
    "refinement_pixels",
    "reprojection_loss",
    "reprojection_residuals",
]

#: the robust losses of :class:`RobustLoss`
ROBUST_LOSSES = ("cauchy", "huber", "squared")

_DEPTH_EPS = 1e-6

#: ``points(times (C, T)) -> (C, T, K, 3)``
PointsFn = Callable[[Tensor], Tensor]


@dataclass(frozen=True)
class RobustLoss:
    """The robust, confidence-weighted loss of one detection's pixel distance ``d = ‖r‖``.

    ``ρ(s)`` of ``s = d²`` (px²), scale ``c``: ``cauchy`` ``c² log(1 + s/c²)``; ``huber``
    ``s`` for ``d ≤ c``, else ``2 c d − c²``; ``squared`` ``s``. A detection counts with
    weight ``confidence`` (or 1 when ``confidence_weighted`` is false) when its confidence
    exceeds ``min_confidence``, else 0.

    Attributes:
        kind: ``"cauchy"`` (default), ``"huber"`` or ``"squared"``.
        scale_px: ``c``, pixels (default 20).
        min_confidence: detections of confidence at or below it are not used (default 0.3).
        confidence_weighted: weight a detection by its confidence (default True).
    """

    kind: str = "cauchy"
    scale_px: float = 20.0
    min_confidence: float = 0.3
    confidence_weighted: bool = True

    def __post_init__(self) -> None:
        if self.kind not in ROBUST_LOSSES:
            raise RefinementError(f"loss.kind: expected one of {list(ROBUST_LOSSES)}, got "
                                  f"{self.kind!r}")
        c = self.scale_px
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not math.isfinite(c) \
                or c <= 0:
            raise RefinementError(f"loss.scale_px: expected a number of pixels > 0, got {c!r}")
        m = self.min_confidence
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not 0 <= m < 1:
            raise RefinementError(f"loss.min_confidence: expected a number in [0, 1), got "
                                  f"{m!r}")
        if not isinstance(self.confidence_weighted, bool):
            raise RefinementError(f"loss.confidence_weighted: expected True or False, got "
                                  f"{self.confidence_weighted!r}")

    @classmethod
    def from_dict(cls, data) -> RobustLoss:
        if isinstance(data, RobustLoss):
            return data
        if data is None:
            return cls()
        if not hasattr(data, "keys"):
            raise RefinementError(f"loss: expected a RobustLoss or a mapping, got {data!r}")
        unknown = sorted(set(data) - {"kind", "scale_px", "min_confidence",
                                      "confidence_weighted"})
        if unknown:
            raise RefinementError(f"loss: unknown setting(s) {unknown}")
        return cls(**dict(data))

    def to_dict(self) -> dict:
        return asdict(self)

    def rho(self, s: Tensor) -> Tensor:
        """``ρ(s)`` of squared pixel distances ``s``."""
        c2 = float(self.scale_px) ** 2
        if self.kind == "cauchy":
            return c2 * torch.log1p(s / c2)
        if self.kind == "huber":
            d = s.clamp_min(0).sqrt()
            return torch.where(s <= c2, s, 2 * self.scale_px * d - c2)
        return s

    def weight(self, s: Tensor) -> Tensor:
        """The IRLS weight ``ρ'(s)`` (1 for small residuals, falling for outliers)."""
        c2 = float(self.scale_px) ** 2
        if self.kind == "cauchy":
            return 1.0 / (1.0 + s / c2)
        if self.kind == "huber":
            d = s.clamp_min(1e-300).sqrt()
            return torch.where(s <= c2, torch.ones_like(s), self.scale_px / d)
        return torch.ones_like(s)

    def detection_weights(self, confidence: Tensor) -> Tensor:
        """Weights of detections of ``confidence`` (``(*)``): 0 at or below the threshold."""
        w = confidence if self.confidence_weighted else torch.ones_like(confidence)
        return torch.where(confidence > self.min_confidence, w, torch.zeros_like(w))


def _check_detections(detections: Tensor, C: int) -> None:
    if not isinstance(detections, Tensor) or detections.dim() != 4 or \
            detections.shape[1] != C or detections.shape[-1] != 3:
        shape = tuple(detections.shape) if isinstance(detections, Tensor) else \
            type(detections).__name__
        raise RefinementError(f"detections: expected shape (T, {C}, K, 3) (u, v, confidence "
                              f"per frame, camera and keypoint), got {shape}")


def interpolation_weights(times: Tensor, num_frames: int) -> tuple[Tensor, Tensor, Tensor]:
    """Catmull–Rom taps of fractional frame ``times`` in a trajectory of ``num_frames``.

    A time ``s = i + u`` (``i`` whole, ``0 ≤ u < 1``) interpolates frames ``i − 1 .. i + 2``
    with the cubic Catmull–Rom weights; frames before the first or after the last are the
    linear extrapolation of the first two or last two. The taps land in four consecutive
    frames ``a .. a + 3``, ``a = clamp(i − 1, 0, F − 4)``.

    Args:
        times: ``(*)`` fractional frame indices (differentiable).
        num_frames: ``F ≥ 4``.

    Returns:
        ``frames (*, 4)`` long, ``weights (*, 4)`` (sum 1) and ``dweights (*, 4)``, the
        derivative of the weights in the time.
    """
    F = num_frames
    if F < 4:
        raise RefinementError(f"points: interpolating in time needs at least 4 frames, got {F}")
    i = torch.floor(times.detach())
    u = times - i
    u2, u3 = u * u, u * u * u
    w = torch.stack([(-u3 + 2 * u2 - u) / 2, (3 * u3 - 5 * u2 + 2) / 2,
                     (-3 * u3 + 4 * u2 + u) / 2, (u3 - u2) / 2], -1)
    dw = torch.stack([(-3 * u2 + 4 * u - 1) / 2, (9 * u2 - 10 * u) / 2,
                      (-9 * u2 + 8 * u + 1) / 2, (3 * u2 - 2 * u) / 2], -1)
    i = i.long()
    a = (i - 1).clamp(0, F - 4)
    q = (i - 1).unsqueeze(-1) + torch.arange(4, device=times.device)  # (*, 4) tap frames
    lo, hi = q < 0, q > F - 1
    m = (q - (F - 1)).to(times.dtype)
    qf = q.to(times.dtype)
    one = torch.ones_like(qf)
    fa = torch.where(lo, torch.zeros_like(q), torch.where(hi, torch.full_like(q, F - 1), q))
    ca = torch.where(lo, 1 - qf, torch.where(hi, 1 + m, one))
    fb = torch.where(lo, torch.ones_like(q), torch.where(hi, torch.full_like(q, F - 2), q))
    cb = torch.where(lo, qf, torch.where(hi, -m, torch.zeros_like(qf)))
    slot_a, slot_b = fa - a.unsqueeze(-1), fb - a.unsqueeze(-1)
    zeros = torch.zeros_like(w)
    weights = zeros.scatter_add(-1, slot_a, w * ca).scatter_add(-1, slot_b, w * cb)
    dweights = zeros.scatter_add(-1, slot_a, dw * ca).scatter_add(-1, slot_b, dw * cb)
    frames = a.unsqueeze(-1) + torch.arange(4, device=times.device)
    return frames, weights, dweights


def interpolate_in_time(points: Tensor, times: Tensor) -> Tensor:
    """A trajectory at fractional frame times (Catmull–Rom, :func:`interpolation_weights`).

    Args:
        points: ``(F, K, 3)`` the points at frames ``0 .. F − 1`` (``F ≥ 4``).
        times: ``(*)`` fractional frames.

    Returns:
        ``(*, K, 3)``, differentiable in ``points`` and ``times``; whole ``times`` inside the
        trajectory give its frames exactly.

    Example:
        >>> X = torch.arange(6.0).reshape(6, 1, 1).expand(6, 1, 3)     # x = frame
        >>> tuple(interpolate_in_time(X, torch.tensor([0.5, 2.25, 6.0]))[:, 0, 0].tolist())
        (0.5, 2.25, 6.0)
    """
    if not isinstance(points, Tensor) or points.dim() != 3 or points.shape[-1] != 3:
        raise RefinementError(f"points: expected shape (T, K, 3), got "
                              f"{tuple(points.shape) if isinstance(points, Tensor) else points}")
    frames, w, _ = interpolation_weights(times.to(points.dtype), points.shape[0])
    return (points[frames] * w[..., None, None]).sum(-3)


def refinement_pixels(points: Tensor, K: Tensor, R: Tensor, t: Tensor, dist: Tensor,
                      per_camera: bool = False) -> Tensor:
    """Pixels of world points in ``C`` cameras, ``(T, C, K, 2)``.

    The model of :func:`~torchmocap.cameras.project_points` (its pixels, inside the lens
    model's monotonic radius), written so that every camera parameter, ``k1`` and ``k2``
    included, has its derivative even where the distortion is zero.

    Args:
        points: ``(T, K, 3)`` seen by every camera, or with ``per_camera`` ``(C, T, K, 3)``
            (camera ``c`` sees ``points[c]``).
        K, R, t, dist: ``(C, 3, 3)``, ``(C, 3, 3)``, ``(C, 3)``, ``(C, 5)``.
        per_camera: whether ``points`` has a leading camera dim.

    Returns:
        ``(T, C, K, 2)`` pixels (u, v) in the promoted dtype of ``points`` and the cameras;
        depth clamped at 1e-6 (points behind a camera get finite pixels).
    """
    dt = torch.promote_types(points.dtype, R.dtype)
    if points.dtype != dt or R.dtype != dt:
        points, K, R, t, dist = (x.to(dt) for x in (points, K, R, t, dist))
    if per_camera:
        pc = torch.einsum("cij,ctkj->tcki", R, points) + t[None, :, None, :]
    else:
        pc = torch.einsum("cij,tkj->tcki", R, points) + t[None, :, None, :]
    z = pc[..., 2:3].clamp_min(_DEPTH_EPS)
    xy = distort_normalized(pc[..., :2] / z, dist)
    fx, s, cx = (K[:, 0, j][None, :, None] for j in range(3))
    fy, cy = K[:, 1, 1][None, :, None], K[:, 1, 2][None, :, None]
    return torch.stack([fx * xy[..., 0] + s * xy[..., 1] + cx, fy * xy[..., 1] + cy], -1)


def reprojection_residuals(points: Tensor | PointsFn, detections: Tensor, K: Tensor, R: Tensor,
                           t: Tensor, dist: Tensor, time_offsets: Tensor | None = None
                           ) -> Tensor:
    """Projections minus detections, ``(T, C, K, 2)`` pixels.

    Args:
        points: ``(T, K, 3)`` world points per frame and keypoint, or a callable
            ``points(times (C, T)) -> (C, T, K, 3)``: the points camera ``c`` sees at its
            frame ``t``, at the subject's time ``times[c, t] = t + δ_c``.
        detections: ``(T, C, K, 3)`` (u, v, confidence); only u, v are read.
        K, R, t, dist: the cameras (``(C, 3, 3)``, ``(C, 3, 3)``, ``(C, 3)``, ``(C, 5)``).
        time_offsets: ``(C,)`` frames, or None (every camera on the subject's clock). With a
            tensor ``points`` the trajectory is interpolated in time
            (:func:`interpolate_in_time`, which needs ``T ≥ 4``).

    Returns:
        ``(T, C, K, 2)`` residuals ``projection − detection`` (missed detections give
        meaningless residuals: weight them 0).
    """
    C = K.shape[0]
    _check_detections(detections, C)
    T = detections.shape[0]
    dt = detections.dtype
    if callable(points) and not isinstance(points, Tensor):
        frames = torch.arange(T, dtype=dt, device=detections.device).expand(C, T)
        times = frames + (0 if time_offsets is None else time_offsets.to(dt)[:, None])
        X = points(times)
        if not isinstance(X, Tensor) or X.shape[:2] != (C, T) or X.dim() != 4 or \
                X.shape[-1] != 3:
            raise RefinementError(f"points: the callable must return (C, T, K, 3) = ({C}, {T}, "
                                  f"K, 3), got {tuple(X.shape) if isinstance(X, Tensor) else X}")
        pix = refinement_pixels(X, K, R, t, dist, per_camera=True)
    else:
        if not isinstance(points, Tensor) or points.shape != (T, detections.shape[2], 3):
            shape = tuple(points.shape) if isinstance(points, Tensor) else type(points).__name__
            raise RefinementError(f"points: expected shape ({T}, {detections.shape[2]}, 3) "
                                  f"(T, K, 3) or a callable, got {shape}")
        if time_offsets is None:
            pix = refinement_pixels(points, K, R, t, dist)
        else:
            frames = torch.arange(T, dtype=points.dtype, device=points.device)
            times = frames[None, :] + time_offsets.to(points.dtype)[:, None]
            pix = refinement_pixels(interpolate_in_time(points, times), K, R, t, dist,
                                    per_camera=True)
    return pix - detections[..., :2].to(pix.dtype)


def reprojection_loss(points: Tensor | PointsFn, detections: Tensor, K: Tensor, R: Tensor,
                      t: Tensor, dist: Tensor, time_offsets: Tensor | None = None,
                      loss: RobustLoss | None = None, noise_px: float = 1.0) -> Tensor:
    """``½ Σ w ρ(‖r‖²) / σ²`` over the detections (:class:`RobustLoss`), a scalar.

    Args:
        points, detections, K, R, t, dist, time_offsets: as in :func:`reprojection_residuals`.
        loss: the robust loss (default :class:`RobustLoss`).
        noise_px: ``σ``, the detections' noise in pixels (their residuals are whitened by it,
            so that the loss adds to :func:`prior_loss`).

    Returns:
        a scalar, differentiable in the points (or what the callable depends on) and the
        cameras. Detections of weight 0 do not take part (a NaN residual there stays out).
    """
    loss = RobustLoss() if loss is None else loss
    r = reprojection_residuals(points, detections, K, R, t, dist, time_offsets)
    w = loss.detection_weights(detections[..., 2].to(r.dtype))
    s = (r * r).sum(-1)
    used = w > 0
    rho = loss.rho(torch.where(used, s, torch.zeros_like(s)))
    return 0.5 * (w * rho).sum() / float(noise_px) ** 2


def prior_loss(free: Tensor, widths: Tensor) -> Tensor:
    """``½ Σ (z / width)²`` of refined parameters ``free (n,)`` (``widths`` inf = no prior)."""
    return 0.5 * ((free / widths.to(free)) ** 2).sum()


class RigRefinement(nn.Module):
    """A rig's refined parameters as an ``nn.Parameter``, and their loss for any 3D points.

    The parameter ``y (n_y,)`` (float64, the gauge already removed:
    :class:`~torchmocap.cameras.rig_parameters.RigParametrization`) starts at the given
    calibration. ``forward(points, detections)`` is :func:`reprojection_loss` of the refined
    cameras (time offsets included when refined) plus :func:`prior_loss`.

    Args:
        rig: the given calibration.
        groups, gauge, time_gauge: as in
            :class:`~torchmocap.cameras.rig_parameters.RigParametrization`.
        priors: :class:`~torchmocap.cameras.rig_priors.RigPriors`.
        loss: :class:`RobustLoss`.
        noise_px: the detections' noise σ (px).

    Example:
        >>> from torchmocap.cameras import make_ring_rig
        >>> m = RigRefinement(make_ring_rig(3), groups=("rotation", "focal"))
        >>> X = torch.rand(4, 5, 3, dtype=torch.float64) + torch.tensor([0.0, 0.0, 0.5])
        >>> det = torch.cat([m.rig().double().project(X)[0],
        ...                  torch.ones(4, 3, 5, 1, dtype=torch.float64)], -1)
        >>> round(float(m(X, det).detach()), 9)
        0.0
    """

    def __init__(self, rig: CameraRig, groups: Sequence[str] = DEFAULT_GROUPS,
                 priors: RigPriors | None = None, loss: RobustLoss | None = None,
                 gauge: str | int = "mean", time_gauge: str | int = "mean",
                 noise_px: float = 1.0) -> None:
        super().__init__()
        self.parametrization = par = RigParametrization(rig, groups, gauge, time_gauge)
        self.priors = RigPriors.from_dict(priors)
        self.loss = RobustLoss.from_dict(loss)
        if isinstance(noise_px, bool) or not isinstance(noise_px, (int, float)) or \
                not math.isfinite(noise_px) or noise_px <= 0:
            raise RefinementError(f"noise_px: expected a number of pixels > 0, got "
                                  f"{noise_px!r}")
        self.noise_px = float(noise_px)
        self.y = nn.Parameter(torch.zeros(par.num_parameters, dtype=torch.float64,
                                          device=par.K.device))
        for name in ("K", "R", "t", "dist"):
            self.register_buffer(f"base_{name}", getattr(par, name).clone())
        self.register_buffer("value_map", par.value_map())
        self.register_buffer("free_index", par.free_camera * 13 + par.free_value)
        self.register_buffer("prior_widths", self.priors.widths(par))

    def values(self) -> Tensor:
        """``(C, 13)`` values of the current parameters."""
        return torch.einsum("cvy,y->cv", self.value_map.to(self.y), self.y)

    def cameras(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``K, R, t, dist`` of the current parameters (differentiable)."""
        return apply_rig_parameters(self.values(), self.base_K, self.base_R, self.base_t,
                                    self.base_dist)

    def time_offsets(self) -> Tensor:
        """``(C,)`` frames."""
        return self.values()[:, 12]

    def rig(self) -> CameraRig:
        """The refined :class:`CameraRig` (detached)."""
        return self.parametrization.refined_rig(self.values())

    def forward(self, points: Tensor | PointsFn, detections: Tensor) -> Tensor:
        v = self.values()
        K, R, t, dist = apply_rig_parameters(v, self.base_K, self.base_R, self.base_t,
                                             self.base_dist)
        offsets = v[:, 12] if self.parametrization.refines_time else None
        data = reprojection_loss(points, detections, K, R, t, dist, offsets, self.loss,
                                 self.noise_px)
        return data + prior_loss(v.reshape(-1)[self.free_index], self.prior_widths)
