"""Projection of particles onto a box of limits (joint limits), by clamping or reflection."""

from __future__ import annotations

import math

import torch

__all__ = ["BOUNDARIES", "as_bound", "bound_particles"]

#: Boundary modes of :func:`bound_particles` (``"none"`` leaves particles as they are).
BOUNDARIES = ("clamp", "reflect", "none")


def as_bound(b, like: torch.Tensor, name: str, fill: float) -> torch.Tensor:
    """``b`` as a ``(D,)`` tensor like ``like`` (``None`` -> ``fill``); typed errors."""
    d = like.shape[-1]
    if b is None:
        return torch.full((d,), fill, dtype=like.dtype, device=like.device)
    t = torch.as_tensor(b, dtype=like.dtype, device=like.device)
    if t.dim() == 0:
        t = t.expand(d)
    if t.shape != (d,):
        raise ValueError(f"{name}: expected a scalar or shape ({d},), got {tuple(t.shape)}")
    if bool(torch.isnan(t).any()):
        raise ValueError(f"{name}: contains NaN")
    return t


def bound_particles(
    x: torch.Tensor,
    lower: torch.Tensor | float | None = None,
    upper: torch.Tensor | float | None = None,
    mode: str = "clamp",
) -> torch.Tensor:
    """Project particles ``x (..., D)`` onto the box ``[lower, upper]`` (each ``(D,)``, ±inf ok).

    ``mode="clamp"`` clamps; ``"none"`` returns ``x`` unchanged; ``mode="reflect"`` folds the
    excess back into the box (a particle 0.1 above ``upper`` lands 0.1 below it; far excursions
    fold repeatedly, period ``2·(upper − lower)``), which keeps diffused particles off the
    boundary.
    """
    if mode not in BOUNDARIES:
        raise ValueError(f"mode: expected one of {BOUNDARIES}, got {mode!r}")
    if mode == "none":
        return x
    lo = as_bound(lower, x, "lower", -math.inf)
    hi = as_bound(upper, x, "upper", math.inf)
    if bool((lo > hi).any()):
        raise ValueError("lower: must not exceed upper")
    if mode == "clamp":
        return torch.maximum(torch.minimum(x, hi), lo)
    flo, fhi = torch.isfinite(lo), torch.isfinite(hi)
    lo0 = torch.where(flo, lo, torch.zeros_like(lo))
    hi0 = torch.where(fhi, hi, torch.zeros_like(hi))
    width = hi0 - lo0
    safe_w = torch.where(width > 0, width, torch.ones_like(width))
    t = torch.remainder(x - lo0, 2 * safe_w)
    both = lo0 + safe_w - (t - safe_w).abs()
    both = torch.where(width > 0, both, lo0.expand_as(x))
    only_lo = lo0 + (x - lo0).abs()
    only_hi = hi0 - (hi0 - x).abs()
    out = torch.where(flo & fhi, both, torch.where(flo, only_lo, torch.where(fhi, only_hi, x)))
    return out
