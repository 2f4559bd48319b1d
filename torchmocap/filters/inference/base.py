"""The per-frame inference interface: an inference module is called once per frame as

    ``inference(energy, proposal, estimator, context, num, generator) -> InferenceResult``

with ``energy`` a ``theta (P, D) -> (P,)`` callable (a bound likelihood,
:class:`~torchmocap.likelihoods.FrameEnergy`), ``proposal`` a
:class:`~torchmocap.proposals.Proposal` (the initial spread and the mutation kernel), ``estimator``
an :class:`~torchmocap.filters.Estimator`, ``context`` the frame's
:class:`~torchmocap.proposals.ProposalContext` (``previous`` = the prediction or the previous
particles; ``previous_frame`` = the tracker's state) and ``num`` the particle count. It returns
the estimate, the final particles and weights, and diagnostics.

The algorithms: :class:`~torchmocap.filters.AnnealedInference` (annealed particle optimisation),
:class:`~torchmocap.filters.LocalInference` (local descent),
:class:`~torchmocap.filters.SIRInference` (sequential importance resampling) and
:class:`~torchmocap.filters.MixtureInference` (mixture density propagation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

__all__ = ["Inference", "InferenceResult", "check_fraction", "summarise_stats"]

_SUMMED_STATS = ("tries", "accepted", "rounds", "gimbal", "resampled")


@dataclass
class InferenceResult:
    """Output of an inference module for one frame.

    Attributes:
        estimate: ``(D,)`` point estimate.
        particles: ``(P, D)`` final particles (or the optimised starts).
        log_weights: ``(P,)`` normalised log weights of ``particles`` (None for local descent).
        info: JSON-friendly diagnostics (β and ESS per layer, proposal statistics, timings).
        carry: state the inference keeps for the next frame (tensors, lists, numbers; e.g. the
            components of a mixture); the tracker hands it back as ``context.previous_frame.carry``
            and stores it in checkpoints.
    """

    estimate: torch.Tensor
    particles: torch.Tensor | None = None
    log_weights: torch.Tensor | None = None
    info: dict[str, Any] = field(default_factory=dict)
    carry: dict[str, Any] | None = None


class Inference(nn.Module):
    """Base class of per-frame inference algorithms (see the module docstring).

    ``keeps_hypotheses``: the inference records its kept modes per frame
    (``info["hypotheses"]``, ``"hypothesis_weights"``, ``"mode_energy"``), which a
    :class:`~torchmocap.filters.smoothing.ViterbiSmoother` reads.
    ``differentiates_energy``: it takes gradients of the energy (local descent, a mixture's
    local optimisation and covariances); a tracker refuses it with a likelihood term that has
    none.
    """

    keeps_hypotheses = False
    differentiates_energy = False

    def forward(self, energy, proposal, estimator, context, num: int,
                generator: torch.Generator | None = None) -> InferenceResult:
        raise NotImplementedError(f"{type(self).__name__} must implement forward()")


def check_fraction(name: str, v, lo: float = 0.0, hi: float = 1.0, lo_open=True) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
            or (v <= lo if lo_open else v < lo) or v > hi:
        raise ValueError(f"{name}: expected a number in {'(' if lo_open else '['}{lo}, {hi}], "
                         f"got {v!r}")
    return float(v)


def summarise_stats(stats: list[dict]) -> dict:
    """Per-layer proposal statistics -> one dict (sums of counts, means of rates)."""
    out: dict[str, Any] = {}
    keys = {k for s in stats for k, v in s.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool)}
    for k in sorted(keys):
        vals = [float(s[k]) for s in stats if k in s]
        out[k] = sum(vals) if k in _SUMMED_STATS else sum(vals) / len(vals)
    if "tries" in out and "accepted" in out:
        out["acceptance_rate"] = out["accepted"] / max(out["tries"], 1.0)
    if any("filled" in s for s in stats):
        out["filled_min"] = min(float(s["filled"]) for s in stats if "filled" in s)
    return out
