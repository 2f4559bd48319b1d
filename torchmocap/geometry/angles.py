"""Angles on the circle."""

from __future__ import annotations

import math

import torch

__all__ = ["wrap_angle"]


def wrap_angle(x: torch.Tensor) -> torch.Tensor:
    """Angles ``(...)`` (radians) wrapped to ``[-π, π)``: ``remainder(x + π, 2π) − π``.

    Differentiable (gradient 1 away from the seam). A difference of two angles is wrapped to
    the shorter arc between them.

    Example:
        >>> wrap_angle(torch.tensor([3.5, -3.5, 0.25]))
        tensor([-2.7832,  2.7832,  0.2500])
    """
    return torch.remainder(x + math.pi, 2 * math.pi) - math.pi
