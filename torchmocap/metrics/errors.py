"""Tracking error metrics.

- :func:`orientation_error_deg`: Pons-Moll et al. (2010) eq. 19 — the geodesic angle between the
  tracked and the true orientation of each validation bone (sensor), in degrees, in the accurate
  ``atan2`` form. A sensor-to-bone offset on the right cancels, so bone frames can be compared.
- :func:`mpjpe_mm`: mean per-joint position error in millimetres; ``root=`` aligns the root
  joints first (the root-relative MPJPE of monocular benchmarks, e.g. Human3.6M's protocol #1),
  so a global offset — a monocular camera's depth of the whole body — does not count.
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


def mpjpe_mm(estimated: torch.Tensor, truth: torch.Tensor, root: int | None = None) -> torch.Tensor:
    """Per-frame mean joint distance in millimetres: ``(T, J, 3) x2 -> (T,)``.

    ``root``: index of a joint to align first (each pose translated so that joint is at the
    origin); ``None`` compares the global positions."""
    if estimated.shape != truth.shape:
        raise ValueError(f"truth: expected shape {tuple(estimated.shape)}, got "
                         f"{tuple(truth.shape)}")
    if root is not None:
        J = estimated.shape[-2]
        if isinstance(root, bool) or not isinstance(root, int) or not -J <= root < J:
            raise ValueError(f"root: expected a joint index in [{-J}, {J}), got {root!r}")
        r = root % J
        estimated = estimated - estimated[..., r : r + 1, :]
        truth = truth - truth[..., r : r + 1, :]
    return (estimated - truth).norm(dim=-1).mean(-1) * 1000.0


def summarize_errors(ori_deg: torch.Tensor, bone_names: list[str],
                     mpjpe: torch.Tensor, mpjpe_root_relative: torch.Tensor | None = None) -> dict:
    """JSON-ready summary: ``orientation_error_deg`` {mean, std, per_bone}, ``mpjpe_mm`` and,
    when given, ``mpjpe_root_relative_mm`` {mean, std}."""
    out = {
        "orientation_error_deg": {
            "mean": float(ori_deg.mean()),
            "std": float(ori_deg.std()) if ori_deg.numel() > 1 else 0.0,
            "per_bone": {b: float(ori_deg[:, k].mean()) for k, b in enumerate(bone_names)},
        },
        "mpjpe_mm": _mean_std(mpjpe),
    }
    if mpjpe_root_relative is not None:
        out["mpjpe_root_relative_mm"] = _mean_std(mpjpe_root_relative)
    return out


def _mean_std(v: torch.Tensor) -> dict:
    return {"mean": float(v.mean()), "std": float(v.std()) if v.numel() > 1 else 0.0}
