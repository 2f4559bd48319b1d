"""Test helper: exact capsule silhouettes (every pixel tested against every projected capsule)."""

from __future__ import annotations

import torch

from torchmocap.likelihoods.silhouette import render_capsule_silhouettes


def capsule_masks(body, rig, theta: torch.Tensor) -> torch.Tensor:
    """Masks ``(C, H, W)`` bool of the capsule body at pose ``theta (D,)``."""
    return render_capsule_silhouettes(body, rig, theta)
