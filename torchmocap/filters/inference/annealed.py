"""Annealed particle optimisation as an inference module (Pons-Moll et al. §4.3).

:class:`AnnealedInference` — Deutscher & Reid's annealed particle filter / Gall's interacting
simulated annealing: layer 0 draws ``num`` particles from the proposal around
``context.previous``; every later layer selects by ``exp(−β_k V)`` (β from the ESS schedule)
and mutates the selected particles with the same proposal at a per-layer std given by a
diffusion rule (:class:`SpreadDiffusion`: the particles' spread in the proposal's coordinates,
cooled; :class:`ShrinkingDiffusion`: the proposal's own std times ``decay^k``). ``rounds > 1``
restarts from the estimate with a smaller spread and keeps the best (static fits of one frame).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Sequence
from typing import Any

import torch

from torchmocap.filters.inference.base import (
    Inference,
    InferenceResult,
    check_fraction,
    summarise_stats,
)
from torchmocap.filters.optim.anneal import anneal
from torchmocap.filters.optim.resampling import MultinomialResampler, as_resampler
from torchmocap.filters.optim.schedules import as_schedule
from torchmocap.filters.optim.temporal_prior import TemporalPrior
from torchmocap.geometry import wrap_angle
from torchmocap.proposals.base import ProposalContext

__all__ = ["AnnealedInference", "ShrinkingDiffusion", "SpreadDiffusion"]


class SpreadDiffusion:
    """Mutation std from the selected particles' spread (Gall et al.'s ISA, diagonal):
    ``std_k = sqrt(rho · decay^k · var(x) + delta)`` per coordinate of the proposal.

    Args:
        rho: scale of the sample variance at the first mutation.
        decay: per-mutation factor on ``rho``; default ``0.1^(1/(K−2))`` (cooled 10× over the
            ``K`` layers: with a constant ρ the ESS schedule keeps the cloud at a constant
            spread, measured in tests/filters/test_annealed.py).
        delta: variance floor (coordinate units squared).
        floor: lower bound on the std as a fraction of the proposal's own std (its initial
            spread) — keeps late layers from collapsing onto one basin; 0 = none.
    """

    def __init__(self, rho: float = 0.5, decay: float | None = None, delta: float = 1e-8,
                 floor: float = 0.0) -> None:
        if not (isinstance(rho, (int, float)) and math.isfinite(rho) and rho > 0):
            raise ValueError(f"rho: expected a positive number, got {rho!r}")
        if decay is not None:
            decay = check_fraction("decay", decay)
        if not (isinstance(delta, (int, float)) and math.isfinite(delta) and delta >= 0):
            raise ValueError(f"delta: expected a number >= 0, got {delta!r}")
        if not (isinstance(floor, (int, float)) and math.isfinite(floor) and floor >= 0):
            raise ValueError(f"floor: expected a number >= 0, got {floor!r}")
        self.rho, self.decay, self.delta, self.floor = float(rho), decay, float(delta), \
            float(floor)

    def __call__(self, coords: torch.Tensor, step: int, layers: int, proposal) -> dict:
        decay = self.decay if self.decay is not None else 0.1 ** (1.0 / max(layers - 2, 1))
        x = coords.to(torch.float64)
        var = (x - x.mean(0, keepdim=True)).square().sum(0) / max(x.shape[0] - 1, 1)
        std = (self.rho * decay**step * var + self.delta).sqrt()
        own = getattr(proposal, "coordinate_std", None)
        if self.floor > 0 and own is not None:
            std = torch.maximum(std, self.floor * own.to(std))
        return {"std": std.to(coords.dtype)}

    def __repr__(self) -> str:
        return (f"SpreadDiffusion(rho={self.rho}, decay={self.decay}, delta={self.delta}, "
                f"floor={self.floor})")


class ShrinkingDiffusion:
    """Mutation std = the proposal's own std times ``decay^k`` (PARSEC bodytrack: ``√α`` with
    α = 0.5 per layer; VXL: 0.5)."""

    def __init__(self, decay: float = math.sqrt(0.5)) -> None:
        self.decay = check_fraction("decay", decay)

    def __call__(self, coords: torch.Tensor, step: int, layers: int, proposal) -> dict:
        return {"scale": self.decay**step, "std": None}

    def __repr__(self) -> str:
        return f"ShrinkingDiffusion(decay={self.decay})"


def _check_starts(refine_from, names: tuple[str, ...]) -> tuple[str, ...]:
    """``refine_from`` as a tuple of distinct start names (see :class:`AnnealedInference`)."""
    if isinstance(refine_from, str):
        refine_from = (("estimate", "prediction") if refine_from == "estimate_and_prediction"
                       else (refine_from,))
    starts = tuple(refine_from)
    bad = [n for n in starts if n not in names]
    if not starts or bad or len(set(starts)) != len(starts):
        raise ValueError(f"refine_from: expected distinct names among {names} (or "
                         f"'estimate_and_prediction'), got {refine_from!r}")
    return starts


class AnnealedInference(Inference):
    """Annealed particle optimisation with a proposal as the mutation kernel.

    Args:
        layers: ``K`` layers (energy evaluations of ``num`` particles).
        schedule: an annealing schedule object (default
            :class:`~torchmocap.filters.ESSSchedule` with α = 0.5: β so that the ESS fraction
            of the weights is α, as in every public implementation).
        selection: a resampler object (default :class:`~torchmocap.filters.MultinomialResampler`).
        diffusion: :class:`SpreadDiffusion` (default) or :class:`ShrinkingDiffusion`.
        rounds: restarts; round ``r`` starts from the previous round's result with the
            proposal's spread scaled by ``round_scale^r``, and the lowest-energy result of all
            rounds is kept (for one-frame fits from a rough start).
        round_scale: see ``rounds``.
        propagate: where layer 0 starts: ``"prediction"`` — ``num`` draws around the predicted
            pose; ``"particles"`` — the previous frame's final particle set, drawn by its
            weights and moved by the prediction's displacement (the AR prediction applied to
            the set, Pons-Moll §4.3: "the initial particles are predicted from the particles
            in the previous frame"), which keeps several hypotheses alive across frames.
        motion_scale: widens layer 0's spread with the motion: per coordinate
            ``sqrt(own_std² + (motion_scale · |Δ|)²)`` with ``Δ`` the predicted displacement
            (prediction − last estimate) in the proposal's coordinates; 0 = the proposal's own
            std only. Fast limbs (100° in 0.16 s) outrun a fixed 3° spread.
        refine: optional second stage (e.g. :class:`LocalInference`) started at the annealed
            estimate — global search, then local refinement of the same energy (Gall et al.,
            "Optimization and filtering for human motion capture", IJCV 2010). Its result is
            the estimate; the particles and weights carried to the next frame stay the
            annealer's. The energy must then be differentiable (a smooth likelihood).
        refine_from: where ``refine`` starts — one name or a list of names among
            ``"estimate"`` (the annealed estimate), ``"prediction"`` (the prediction
            ``context.previous``, the LS baseline's start) and ``"last_estimate"`` (the previous
            frame's estimate, ``context.last_estimate``: no momentum); every start is
            descended in one batch and the lowest final energy is kept — the annealer's basin or
            the one a local descent from the dynamics finds. ``"estimate_and_prediction"`` is
            short for ``["estimate", "prediction"]``.
        prior_std_deg: optional Gaussian temporal prior about ``θ̂`` (see ``prior_mean``): every
            layer's weights are multiplied by ``exp(−½ Σ (wrap(θ − θ̂) / σ)²)`` — not tempered by β —
            with ``σ`` = this angle on every rotation DoF and ``prior_translation_std`` metres on
            the root translation (:class:`~torchmocap.filters.TemporalPrior`).
            None: off (the paper's weights). ``refine`` descends the energy alone.
        prior_translation_std: see ``prior_std_deg``.
        prior_mean: ``"prediction"`` (the AR prediction, the dynamics' own mean),
            ``"last_estimate"`` (the previous frame's estimate: no momentum, so an estimate held
            near the prior cannot feed the AR extrapolation that centres the next one), or a
            number ``a`` in ``[0, 1]``: the point ``a`` of the way from the previous estimate to
            the prediction (angles along the shorter arc; 0 = ``"last_estimate"``,
            1 = ``"prediction"``) — damped momentum.
        skeleton: the tracking model (runtime; which DoFs are translations), needed with
            ``prior_std_deg``.
    """

    PROPAGATE = ("prediction", "particles")
    REFINE_FROM = ("estimate", "prediction", "last_estimate")

    def __init__(self, layers: int = 15, schedule=None, selection=None,
                 diffusion=None, rounds: int = 1, round_scale: float = 0.5,
                 propagate: str = "prediction", motion_scale: float = 0.0,
                 refine: Inference | None = None, prior_std_deg: float | None = None,
                 prior_translation_std: float = 0.1, prior_mean: str | float = "prediction",
                 skeleton=None, refine_from: str | Sequence[str] = "estimate") -> None:
        super().__init__()
        self.refine_from = _check_starts(refine_from, self.REFINE_FROM)
        names = {"prediction": 1.0, "last_estimate": 0.0}
        if isinstance(prior_mean, str) and prior_mean in names:
            blend = names[prior_mean]
        elif (isinstance(prior_mean, (int, float)) and not isinstance(prior_mean, bool)
              and 0.0 <= prior_mean <= 1.0):
            blend = float(prior_mean)
        else:
            raise ValueError(f"prior_mean: expected 'prediction', 'last_estimate' or a number "
                             f"in [0, 1], got {prior_mean!r}")
        self.prior_mean, self._prior_blend = prior_mean, blend
        self.prior_std_deg = prior_std_deg
        self.temporal_prior = None
        if prior_std_deg is not None:
            if skeleton is None:
                raise ValueError("skeleton: required with prior_std_deg (which DoFs are "
                                 "translations)")
            self.temporal_prior = TemporalPrior.for_skeleton(skeleton, prior_std_deg,
                                                             prior_translation_std)
        if refine is not None and not isinstance(refine, Inference):
            raise TypeError(f"refine: expected an Inference module (e.g. LocalInference) or "
                            f"None, got {type(refine).__name__}")
        self.refine = refine
        if propagate not in self.PROPAGATE:
            raise ValueError(f"propagate: expected one of {self.PROPAGATE}, got {propagate!r}")
        if not (isinstance(motion_scale, (int, float)) and math.isfinite(motion_scale)
                and motion_scale >= 0):
            raise ValueError(f"motion_scale: expected a number >= 0, got {motion_scale!r}")
        self.propagate = propagate
        self.motion_scale = float(motion_scale)
        for name, v in (("layers", layers), ("rounds", rounds)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        self.layers, self.rounds = layers, rounds
        self.round_scale = check_fraction("round_scale", round_scale)
        self.schedule = as_schedule(schedule)
        self.selection = as_resampler(selection, "selection", MultinomialResampler)
        self.diffusion = SpreadDiffusion() if diffusion is None else diffusion
        if not callable(self.diffusion):
            raise TypeError(f"diffusion: expected a diffusion rule, got "
                            f"{type(self.diffusion).__name__}")

    def _start(self, proposal, context) -> ProposalContext:
        """Layer 0's context: the prediction or the propagated particle set, and its spread."""
        last = context.last_estimate
        prev = context.previous
        ctx = context
        if last is not None and prev.dim() == 1 and (self.motion_scale > 0
                                                      or self.propagate == "particles"):
            delta = prev - last.to(prev)
            # an angle that wrapped by 2 pi between the estimate and the prediction
            delta = torch.where(delta.abs() > math.pi, wrap_angle(delta), delta)
            own = proposal.coordinate_std
            if self.motion_scale > 0 and own is not None:
                d = proposal.coordinates(delta[None])[0].abs() * self.motion_scale
                std = (own.to(d).square() + d.square()).sqrt() * context.scale
                ctx = dataclasses.replace(ctx, std=std)
            past = context.previous_frame
            parts = None if past is None else past.particles
            if self.propagate == "particles" and parts is not None and parts.dim() == 2:
                ctx = dataclasses.replace(ctx, previous=parts.to(prev) + delta,
                                          log_weights=past.log_weights)
        return ctx

    def _one_round(self, energy, proposal, estimator, context, num, generator, start=None,
                   prior=None):
        stats: list[dict] = []

        def diffuse(x, step, g):
            fields = self.diffusion(proposal.coordinates(x), step, self.layers, proposal)
            ctx = dataclasses.replace(context, previous=x, log_weights=None, **fields)
            out = proposal.sample(ctx, x.shape[0], g)
            stats.append(out.stats)
            return out.particles

        first = proposal.sample(start if start is not None else context, num, generator)
        stats.append(first.stats)
        res = anneal(energy, first.particles, layers=self.layers, schedule=self.schedule,
                     selection=self.selection, diffusion=diffuse, boundary="clamp",
                     mean_fn=lambda x, w: estimator(x, w, context), generator=generator,
                     log_prior=None if prior is None else (lambda x: -prior(x)))
        return res, stats

    def prior_centre(self, context) -> torch.Tensor:
        """The temporal prior's mean ``(D,)`` for ``context`` (see ``prior_mean``): the
        prediction ``context.previous``, the previous estimate
        ``context.last_estimate`` (when the tracker passes one), or the point
        ``prior_mean`` of the way between them."""
        mean = context.previous
        last = context.last_estimate
        if self._prior_blend < 1.0 and last is not None:
            last = last.to(mean)
            # last estimate -> prediction, angles along the shorter arc
            d = (mean - last if self.temporal_prior is None
                 else self.temporal_prior.difference(mean, last))
            mean = last + self._prior_blend * d
        return mean

    def forward(self, energy, proposal, estimator, context, num: int,
                generator: torch.Generator | None = None) -> InferenceResult:
        t0 = time.perf_counter()
        prior = None
        if self.temporal_prior is not None and context.previous.dim() == 1:
            centre = self.prior_centre(context).detach()
            prior = functools.partial(self.temporal_prior.energy, mean=centre)
        best = None
        info: dict[str, Any] = {"beta": [], "ess": [], "min_energy": []}
        all_stats: list[dict] = []
        ctx = context
        for r in range(self.rounds):
            if r > 0:
                ctx = dataclasses.replace(context, previous=best[0], log_weights=None,
                                          scale=context.scale * self.round_scale**r)
            start = self._start(proposal, ctx) if r == 0 else None
            res, stats = self._one_round(energy, proposal, estimator, ctx, num, generator,
                                         start, prior)
            all_stats += stats
            info["beta"] += [float(b) for b in res.beta]
            info["ess"] += [float(e) for e in res.ess]
            info["min_energy"] += [float(e) for e in res.min_energy]
            cand = res.estimate
            if self.rounds > 1:  # keep the lowest-energy result over all rounds
                with torch.no_grad():
                    v = energy(torch.stack([res.estimate, res.best]))
                cand, v_c = (res.best, float(v[1])) if v[1] < v[0] else (res.estimate,
                                                                          float(v[0]))
                if best is not None and v_c > best[1]:
                    cand, v_c = best[0], best[1]
                best = (cand, v_c, res)
            else:
                best = (cand, math.nan, res)
        est, _, res = best
        if self.refine is not None:
            starts, names = self._refine_starts(est.detach(), context)
            ctx = dataclasses.replace(context, previous=starts, log_weights=None)
            ref = self.refine(energy, proposal, estimator, ctx, 1, generator)
            info["refine"] = {k: v for k, v in ref.info.items()
                              if isinstance(v, (int, float)) and not isinstance(v, bool)}
            won = int(ref.info.get("start", 0))
            for i, n in enumerate(names):  # averaged over frames: how often each start won
                info["refine"][f"from_{n}"] = float(i == won)
            est = ref.estimate.detach().to(est.dtype)
        info["proposal"] = summarise_stats(all_stats)
        info["seconds_inference"] = time.perf_counter() - t0
        if self.rounds > 1:
            info["rounds"] = self.rounds
            info["seconds_per_round"] = info["seconds_inference"] / self.rounds
        return InferenceResult(estimate=est, particles=res.particles,
                               log_weights=res.log_weights, info=info)

    def _refine_starts(self, est: torch.Tensor, context: ProposalContext
                       ) -> tuple[torch.Tensor, list[str]]:
        """``(S, D)`` starts of the local stage (``(D,)`` for one) and their names, in the order
        of ``refine_from`` (a start the context lacks — no last estimate on the first frame, a
        batched prediction — is left out; the annealed estimate stands in when none is left)."""
        found = {"estimate": est}
        if context.previous.dim() == 1:
            found["prediction"] = context.previous
        last = context.last_estimate
        if torch.is_tensor(last) and last.shape == est.shape:
            found["last_estimate"] = last
        names = [n for n in self.refine_from if n in found] or ["estimate"]
        rows = [found[n].detach().to(est) for n in names]
        return (torch.stack(rows) if len(rows) > 1 else rows[0]), names

    def extra_repr(self) -> str:
        return (f"layers={self.layers}, schedule={self.schedule!r}, "
                f"selection={self.selection!r}, diffusion={self.diffusion!r}, "
                f"rounds={self.rounds}, propagate={self.propagate!r}, "
                f"motion_scale={self.motion_scale}, refine={self.refine is not None}, "
                f"prior_std_deg={self.prior_std_deg}")
