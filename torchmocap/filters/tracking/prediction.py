"""Third-order autoregressive pose prediction (Pons-Moll §4.3: particles are predicted from the
last three estimates), with rotation coordinates composed on SO(3).

History is chronological: ``history (..., T, D)`` with ``T ≥ 3``; only the last three rows are
used, ``x1 = history[..., -1, :]`` (t−1, most recent), ``x2`` (t−2), ``x3`` (t−3). With
``Δ1 = x1 − x2`` and ``Δ2 = x2 − x3``, the scalar modes are

- ``constant_acceleration``: ``x̂ = 3x1 − 3x2 + x3 = x1 + Δ1 + (Δ1 − Δ2)`` (exact on quadratics,
  but it amplifies i.i.d. noise by √19 ≈ 4.4);
- ``damped``: ``x̂ = x1 + λ1 Δ1 + λ2 (Δ1 − Δ2)`` (λ = (1, 1) is constant acceleration, (1, 0)
  constant velocity, (0, 0) constant position).

**Rotation groups.** Angles must not be extrapolated as numbers: a rotation vector that wraps
from +π to −π, or Euler-type angles through arbitrary axes, break linear extrapolation. A
:class:`RotationGroup` names three coordinates; they are mapped to rotations ``R1, R2, R3`` and
the *relative* increments ``δ1 = log(R2ᵀ R1)``, ``δ2 = log(R3ᵀ R2)`` are extrapolated the same
way (``δ̂ = u δ1 + v δ2``; constant acceleration ``u = 2, v = −1``; damped ``u = λ1 + λ2,
v = −λ2``), then composed: ``R̂ = R1 exp(δ̂)``. A constant-rate rotation is predicted exactly.

Finally the prediction is clamped to ``[lower, upper]`` (e.g. ``skeleton.lower/upper``).

Shapes: ``T`` frames of history, ``D`` pose dims, ``G`` rotation groups.

Example:
    >>> h = torch.tensor([[0.0], [1.0], [4.0]])  # x = t², t = 0, 1, 2
    >>> predict_ar3(h, "constant_acceleration")
    tensor([9.])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchmocap.filters.optim.rotations import (
    RotationGroup,
    as_groups,
    skeleton_rotation_groups,
)
from torchmocap.geometry import so3_exp, so3_log

__all__ = ["MODES", "PosePredictor", "predict_ar3"]

MODES = ("constant_acceleration", "damped")



def _check_history(history: torch.Tensor) -> None:
    if not isinstance(history, torch.Tensor) or not history.is_floating_point():
        raise TypeError("history: expected a floating-point torch.Tensor of shape (..., T, D)")
    if history.dim() < 2 or history.shape[-2] < 3 or history.shape[-1] < 1:
        raise ValueError(
            f"history: expected shape (..., T, D) with T >= 3, got {tuple(history.shape)}"
        )
    if not bool(torch.isfinite(history).all()):
        raise ValueError("history: expected finite values, found NaN or inf")


def _check_groups(groups: Sequence[RotationGroup], d: int) -> None:
    seen: set[int] = set()
    for g in groups:
        for i in g.indices:
            if not -d <= i < d:
                raise ValueError(f"rotation_groups: index {i} out of range for D = {d}")
            if i % d in seen:
                raise ValueError(f"rotation_groups: index {i} appears in two groups")
            seen.add(i % d)


def _bound(x: torch.Tensor, lower, upper, name_lo="lower", name_hi="upper") -> torch.Tensor:
    d = x.shape[-1]
    for b, name in ((lower, name_lo), (upper, name_hi)):
        if b is not None:
            t = torch.as_tensor(b, dtype=x.dtype, device=x.device)
            if t.dim() > 1 or (t.dim() == 1 and t.shape[0] != d):
                raise ValueError(f"{name}: expected a scalar or shape ({d},), got {tuple(t.shape)}")
    if lower is not None:
        x = torch.maximum(x, torch.as_tensor(lower, dtype=x.dtype, device=x.device))
    if upper is not None:
        x = torch.minimum(x, torch.as_tensor(upper, dtype=x.dtype, device=x.device))
    return x


def _mode_uv(mode: str, damping: tuple[float, float]) -> tuple[float, float]:
    """Increment extrapolation ``x̂ − x1 = u Δ1 + v Δ2`` of the scalar modes."""
    if mode == "constant_acceleration":
        return 2.0, -1.0
    lam1, lam2 = damping
    return lam1 + lam2, -lam2


def predict_ar3(
    history: torch.Tensor,
    mode: str = "constant_acceleration",
    *,
    damping: tuple[float, float] = (0.8, 0.3),
    rotation_groups: Sequence[RotationGroup | Sequence[int]] = (),
    lower: torch.Tensor | float | None = None,
    upper: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """Predict the next pose from the last three: ``history (..., T, D) -> (..., D)``.

    Args:
        history: chronological poses, ``T ≥ 3`` (the last row is the most recent).
        mode: ``"constant_acceleration"`` or ``"damped"``.
        damping: ``(λ1, λ2)`` of the damped mode (defaults are a heuristic, not the paper's).
        rotation_groups: coordinates composed on SO(3) (see :class:`RotationGroup`; a plain
            triple of indices means a rotation vector).
        lower, upper: limits, scalar or ``(D,)``; the prediction is clamped to them.
    Returns:
        ``(..., D)`` predicted pose.
    """
    _check_history(history)
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    groups = as_groups(rotation_groups)
    d = history.shape[-1]
    _check_groups(groups, d)
    x3, x2, x1 = history[..., -3:, :].unbind(-2)

    u, v = _mode_uv(mode, damping)
    pred = x1 + u * (x1 - x2) + v * (x2 - x3)

    if groups:
        rc = torch.tensor([[u, v]] * len(groups), dtype=history.dtype, device=history.device)
        pred = pred.clone()
        for gi, g in enumerate(groups):
            idx = list(g.indices)
            R1, R2, R3 = g.matrix(x1[..., idx]), g.matrix(x2[..., idx]), g.matrix(x3[..., idx])
            d1 = so3_log(R2.transpose(-1, -2) @ R1)
            d2 = so3_log(R3.transpose(-1, -2) @ R2)
            dh = rc[gi, 0] * d1 + rc[gi, 1] * d2
            Rh = R1 @ so3_exp(dh)
            pred[..., idx] = g.values(Rh, x1[..., idx]).to(pred.dtype)
    return _bound(pred, lower, upper)


class PosePredictor(torch.nn.Module):
    """Next-pose prediction of a tracker from its last estimates (Pons-Moll §4.3).

    With three or more estimates: :func:`predict_ar3` on the last three, the root rotation
    composed on SO(3) (:func:`skeleton_rotation_groups`), clamped to the joint limits. With two:
    half a constant-velocity step; with one: that estimate.

    Args:
        skeleton: the tracking model (limits, root axes).
        mode: ``"damped"`` (default), ``"constant_acceleration"`` or ``"constant_position"``.
        damping: ``(λ1, λ2)`` of the damped mode.

    ``forward(history (T, D)) -> (D,)``, chronological history (most recent last).
    """

    PREDICTOR_MODES = ("damped", "constant_acceleration", "constant_position")

    def __init__(self, skeleton, mode: str = "damped",
                 damping: Sequence[float] = (0.8, 0.3)) -> None:
        super().__init__()
        if mode not in self.PREDICTOR_MODES:
            raise ValueError(f"mode: expected one of {self.PREDICTOR_MODES}, got {mode!r}")
        damping = tuple(float(x) for x in damping)
        if len(damping) != 2:
            raise ValueError(f"damping: expected two numbers (l1, l2), got {damping!r}")
        self.mode = mode
        self.damping = (0.0, 0.0) if mode == "constant_position" else damping
        self.register_buffer("lower", skeleton.lower.detach().clone())
        self.register_buffer("upper", skeleton.upper.detach().clone())
        root = skeleton.joint_names[0]
        groups = (skeleton_rotation_groups(skeleton, [root])
                  if len(skeleton.joint_axes[0]) == 3 else [])
        self._ar_mode = "constant_acceleration" if mode == "constant_acceleration" else "damped"
        self._groups = as_groups(groups)

    def forward(self, history: torch.Tensor) -> torch.Tensor:
        if history.dim() != 2 or history.shape[-1] != self.lower.shape[0]:
            raise ValueError(f"history: expected shape (T, {self.lower.shape[0]}), got "
                             f"{tuple(history.shape)}")
        lo, hi = self.lower.to(history.dtype), self.upper.to(history.dtype)
        if history.shape[0] >= 3 and self.mode != "constant_position":
            pred = predict_ar3(history[-3:].double(), self._ar_mode, damping=self.damping,
                               rotation_groups=self._groups).to(history.dtype)
        elif history.shape[0] == 2 and self.mode != "constant_position":
            pred = history[-1] + 0.5 * (history[-1] - history[-2])
        else:
            pred = history[-1].clone()
        return torch.maximum(torch.minimum(pred, hi), lo)

    def extra_repr(self) -> str:
        return f"mode={self.mode!r}, damping={self.damping}"
