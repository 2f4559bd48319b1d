"""Input validation helpers shared by the geometry functions (messages built only on failure)."""

from __future__ import annotations

import torch


def check_last_dims(x: torch.Tensor, dims: tuple[int, ...], name: str) -> None:
    """Raise ``ValueError`` unless ``x`` is a tensor whose trailing dims equal ``dims``."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    n = len(dims)
    if x.dim() < n or tuple(x.shape[-n:]) != tuple(dims):
        want = "(*, " + ", ".join(str(d) for d in dims) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(x.shape)}")


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise ``ValueError`` if ``x`` holds NaN or infinity."""
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name}: expected finite values, found NaN or inf")


def check_unit_norm(x: torch.Tensor, name: str, tol: float | None = None) -> None:
    """Raise ``ValueError`` unless every vector along the last dim has unit norm."""
    check_finite(x, name)
    if tol is None:
        tol = 1e-3 if x.dtype in (torch.float16, torch.bfloat16, torch.float32) else 1e-6
    if x.numel() and float((x.norm(dim=-1) - 1).abs().max()) > tol:
        raise ValueError(f"{name}: expected unit-norm vectors along the last dim (tolerance {tol})")
