"""Tracking error metrics.

- :func:`orientation_error_deg`: Pons-Moll et al. (2010) eq. 19 — the geodesic angle between the
  tracked and the true orientation of each validation bone (sensor), in degrees, in the accurate
  ``atan2`` form. A sensor-to-bone offset on the right cancels, so bone frames can be compared.
- :func:`mpjpe_mm`: mean per-joint position error in millimetres.
Shapes: ``T`` frames, ``K`` bones, ``J`` joints.
"""

from __future__ import annotations

import math

import torch

from torchmocap.geometry import geodesic_angle

__all__ = ["orientation_error_deg", "mpjpe_mm", "summarize_errors"]


def orientation_error_deg(estimated: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Angles (degrees) between rotations ``(..., 3, 3)``: ``(...)``."""
    if estimated.shape != truth.shape:
        raise ValueError(f"truth: expected shape {tuple(estimated.shape)}, got "
                         f"{tuple(truth.shape)}")
    return geodesic_angle(estimated, truth) * (180.0 / math.pi)


def mpjpe_mm(estimated: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-frame mean joint distance in millimetres: ``(T, J, 3) x2 -> (T,)``."""
    if estimated.shape != truth.shape:
        raise ValueError(f"truth: expected shape {tuple(estimated.shape)}, got "
                         f"{tuple(truth.shape)}")
    return (estimated - truth).norm(dim=-1).mean(-1) * 1000.0


def summarize_errors(ori_deg: torch.Tensor, bone_names: list[str],
                     mpjpe: torch.Tensor) -> dict:
    """JSON-ready summary: ``orientation_error_deg`` {mean, std, per_bone}, ``mpjpe_mm``."""
    return {
        "orientation_error_deg": {
            "mean": float(ori_deg.mean()),
            "std": float(ori_deg.std()) if ori_deg.numel() > 1 else 0.0,
            "per_bone": {b: float(ori_deg[:, k].mean()) for k, b in enumerate(bone_names)},
        },
        "mpjpe_mm": {
            "mean": float(mpjpe.mean()),
            "std": float(mpjpe.std()) if mpjpe.numel() > 1 else 0.0,
        },
    }
