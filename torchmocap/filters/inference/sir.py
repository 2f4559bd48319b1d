"""Sequential importance resampling as an inference module (Hauberg & Pedersen §1.1): one
:func:`~torchmocap.filters.optim.sir.sir_step` per frame, the particle set carried between
frames."""

from __future__ import annotations

import dataclasses
import math
import time

import torch

from torchmocap.filters.inference.base import (
    Inference,
    InferenceResult,
    check_fraction,
    summarise_stats,
)
from torchmocap.filters.optim.resampling import SystematicResampler, as_resampler
from torchmocap.filters.optim.sir import sir_step

__all__ = ["SIRInference"]


class SIRInference(Inference):
    """Sequential importance resampling, one step per frame (Hauberg & Pedersen §1.1, eqs. 1–2).

    The particle set is carried between frames (``context.previous_frame.particles`` and
    ``.log_weights``; the first frame starts from ``num`` copies of ``context.previous``).
    Per frame: resample when the incoming ESS fraction is below ``ess_threshold`` (1 = every
    frame), propose one particle from each (possibly resampled) particle, and weight
    ``w_t ∝ w_{t−1} · p(z_t | θ_t) · r_t`` with ``log p = −V`` (the likelihood's energy) and the
    correction factor ``r_t = p(θ_t | θ_{t−1}) / q(θ_t | z_t, θ_{t−1})`` from the proposal's
    ``log_prior`` and ``log_q`` when it reports both. When it does not (projected and
    data-driven proposals, whose density has no closed form) ``r_t = 1``: the filter is then
    approximate — for rejection-truncated priors (the paper's data-driven proposals) the true
    ``r_t`` is constant, which this is.

    Args:
        selection: resampler object (default :class:`~torchmocap.filters.SystematicResampler`).
        ess_threshold: resample when ESS/P of the incoming weights is below this.
        temperature: the weights use ``−V / temperature`` (1 = the likelihood as it is).

    ``info``: ``ess`` (of the new weights, a one-element list like the annealer's per-layer
    list), ``ess_fraction``, ``resampled``, ``log_evidence`` (``log p̂(z_t | z_{1:t−1})``),
    ``correction`` (whether ``r_t`` was used) and the proposal's statistics.
    """

    def __init__(self, selection=None, ess_threshold: float = 1.0,
                 temperature: float = 1.0) -> None:
        super().__init__()
        self.selection = as_resampler(selection, "selection", SystematicResampler)
        self.ess_threshold = check_fraction("ess_threshold", ess_threshold, lo_open=False)
        if not (isinstance(temperature, (int, float)) and math.isfinite(temperature)
                and temperature > 0):
            raise ValueError(f"temperature: expected a number > 0, got {temperature!r}")
        self.temperature = float(temperature)

    def forward(self, energy, proposal, estimator, context, num: int,
                generator: torch.Generator | None = None) -> InferenceResult:
        t0 = time.perf_counter()
        past = context.previous_frame
        prev = None if past is None else past.particles
        lw = None if past is None else past.log_weights
        if prev is None or prev.dim() != 2 or prev.shape[0] != num:
            start = context.previous if context.previous.dim() == 1 else context.previous[0]
            prev = start.expand(num, -1).clone()
            lw = None
        lw = (torch.full((num,), -math.log(num), dtype=torch.float64, device=prev.device)
              if lw is None else lw.to(torch.float64))
        drawn = []

        def propose(x, g):  # one particle from each (resampled) particle; r_t when known
            ctx = dataclasses.replace(context, previous=x.to(context.previous.dtype),
                                      log_weights=None)
            out = proposal.sample(ctx, num, g)
            drawn.append(out)
            if out.log_q is None or out.log_prior is None:
                return out.particles
            return out.particles, (out.log_prior - out.log_q).to(torch.float64)

        def log_likelihood(x):
            with torch.no_grad():
                return -energy(x).to(torch.float64) / self.temperature

        try:
            st = sir_step(prev, lw, propose, log_likelihood, generator=generator,
                          resampler=self.selection, ess_threshold=self.ess_threshold)
        except ValueError as e:
            if "zero likelihood" in str(e):
                raise ValueError("energy: every particle has zero weight (infinite energies)") \
                    from None
            raise
        out, x = drawn[0], st.particles
        ess = float(st.ess)
        est = estimator(x, st.log_weights.exp().to(x.dtype), context)
        info = {"ess": [ess], "ess_fraction": ess / num, "resampled": st.resampled,
                "log_evidence": float(st.log_evidence),
                "correction": out.log_q is not None and out.log_prior is not None,
                "proposal": summarise_stats([out.stats]),
                "seconds_inference": time.perf_counter() - t0}
        if getattr(out, "valid", None) is not None:
            info["proposal"]["valid_fraction"] = float(out.valid.float().mean())
        return InferenceResult(estimate=est, particles=x.detach(),
                               log_weights=st.log_weights.to(x.dtype), info=info)

    def extra_repr(self) -> str:
        return (f"selection={self.selection!r}, ess_threshold={self.ess_threshold}, "
                f"temperature={self.temperature}")
