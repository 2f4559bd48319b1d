"""Local descent of a differentiable energy as an inference module (the L/LS baselines of
Pons-Moll et al., and the refinement stage of the refined presets)."""

from __future__ import annotations

import dataclasses
import math
import time

import torch

from torchmocap.filters.inference.base import Inference, InferenceResult
from torchmocap.filters.optim.local import check_method, minimise_local

__all__ = ["LocalInference"]


class LocalInference(Inference):
    """Local descent of a differentiable energy from the prediction (the L/LS baselines).

    Args:
        skeleton: the tracking model (its joint limits bound the descent).
        method: ``"adam"`` (clamped after each step) or ``"lbfgs"`` (projected, per problem).
        iterations: steps.
        lr: Adam learning rate (radians / metres per step).
        starts: ``1`` = the prediction only; ``n > 1`` adds ``n − 1`` proposal draws around it
            and keeps the lowest-energy result.

    ``context.previous`` is the start ``(D,)``, or several ``(K, D)`` (all descended, in one
    batch; the lowest final energy is the estimate).
    """

    differentiates_energy = True

    def __init__(self, skeleton, method: str = "adam", iterations: int = 40, lr: float = 0.02,
                 starts: int = 1) -> None:
        super().__init__()
        check_method(method)  # one of minimise_local's OPTIMISERS
        for name, v in (("iterations", iterations), ("starts", starts)):
            if isinstance(v, bool) or not isinstance(v, int) or v < (0 if name == "iterations"
                                                                      else 1):
                raise ValueError(f"{name}: expected an int >= {0 if name == 'iterations' else 1}"
                                 f", got {v!r}")
        if not (isinstance(lr, (int, float)) and math.isfinite(lr) and lr > 0):
            raise ValueError(f"lr: expected a positive number, got {lr!r}")
        self.method, self.iterations, self.lr, self.starts = method, iterations, float(lr), starts
        self.register_buffer("lower", skeleton.lower.detach().clone())
        self.register_buffer("upper", skeleton.upper.detach().clone())

    def forward(self, energy, proposal, estimator, context, num: int,
                generator: torch.Generator | None = None) -> InferenceResult:
        t0 = time.perf_counter()
        prev = context.previous
        x0 = prev[None] if prev.dim() == 1 else prev
        if self.starts > 1:
            ctx = context if prev.dim() == 1 else dataclasses.replace(context, previous=prev[0])
            extra = proposal.sample(ctx, self.starts - 1, generator).particles
            x0 = torch.cat([x0, extra.to(x0.dtype)])
        lo, hi = self.lower.to(x0.dtype), self.upper.to(x0.dtype)
        res = minimise_local(energy, x0, method=self.method, iterations=self.iterations,
                             lower=lo, upper=hi, lr=self.lr)
        i = int(torch.argmin(res.energy))
        info = {"final_energy": float(res.energy[i]), "start_energy": float(res.trace[0, i]),
                "iterations": res.iterations, "start": i,
                "seconds_inference": time.perf_counter() - t0}
        return InferenceResult(estimate=res.x[i].detach(), particles=res.x.detach(),
                               log_weights=None, info=info)

    def extra_repr(self) -> str:
        return (f"method={self.method!r}, iterations={self.iterations}, lr={self.lr}, "
                f"starts={self.starts}")
