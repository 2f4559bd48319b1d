"""Marker-to-skin error (Hauberg & Pedersen 2011, eq. 16).

``E = 1/(T M) Σ_t Σ_m D(θ̂_t, v_m)``: the orthogonal distance between each motion-capture
marker ``v_m`` (a point on the observed body's skin) and the estimated skin — the union of the
tracking model's capsules — averaged over frames and markers. Shapes: ``T`` frames, ``M``
markers, ``B`` capsules.
"""

from __future__ import annotations

import torch

from torchmocap.body.capsules import capsule_distance

__all__ = ["marker_skin_distance"]


def marker_skin_distance(markers: torch.Tensor, endpoints: torch.Tensor, radii: torch.Tensor
                         ) -> torch.Tensor:
    """``(T, M)`` unsigned distances (metres) of ``markers (T, M, 3)`` to the skin of capsule
    axes ``endpoints (T, B, 2, 3)`` with ``radii (B,)``."""
    if markers.dim() != 3 or markers.shape[-1] != 3:
        raise ValueError(f"markers: expected shape (T, M, 3), got {tuple(markers.shape)}")
    if endpoints.shape[0] != markers.shape[0]:
        raise ValueError(f"endpoints: expected {markers.shape[0]} frames, got "
                         f"{endpoints.shape[0]}")
    return capsule_distance(markers.to(endpoints), endpoints, radii).abs()
