"""Capped, vectorised rejection sampling around any proposal (Pons-Moll et al.'s RS baseline).

:class:`RejectionProposal` draws candidates from an inner proposal and keeps those whose
per-sensor angular error is at most ``threshold_deg`` for *every* sensor (10 deg in the paper).
Unlike pyro's rejection sampler it never loops forever: it stops at ``max_tries`` candidates,
``max_rounds`` rounds or ``max_seconds``, fills the remaining slots with the best candidates seen
(smallest worst-sensor error) and flags them ``valid = False``. Candidates are drawn in batches
sized from the running acceptance rate. ``stats``: ``acceptance_rate`` (accepted / tries),
``tries``, ``accepted``, ``rounds``, ``filled`` (fraction of valid slots),
``per_sensor_acceptance`` ``(S,)``, ``seconds``, ``stopped`` (why it stopped).

For an inner proposal that truncates a prior, the accepted particles are exact draws from the
prior restricted to the constraint set, so the SIR correction factor is a constant (Hauberg &
Pedersen §2).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import torch

from torchmocap.geometry.rotations import geodesic_angle
from torchmocap.ik.sensor_manifold import SensorManifold, sensor_rotations
from torchmocap.proposals.base import Proposal, ProposalContext, Proposed

__all__ = ["RejectionProposal", "SensorAngleCriterion"]

ErrorFn = Callable[[torch.Tensor, ProposalContext], torch.Tensor]


class SensorAngleCriterion:
    """Per-sensor angular error (radians) ``(P, S)`` between the bone orientations of poses
    ``theta (P, D)`` and the sensor-bone orientations ``R_TS R_SB`` of ``context.sensors``
    (the calibrated tracking sensors of ``manifold``)."""

    requires = ("imu",)

    def __init__(self, manifold: SensorManifold) -> None:
        if not isinstance(manifold, SensorManifold):
            raise TypeError(f"manifold: expected a SensorManifold, got {type(manifold).__name__}")
        self.manifold = manifold

    def __call__(self, theta: torch.Tensor, context: ProposalContext) -> torch.Tensor:
        m = self.manifold
        if context.sensors is None:
            raise ValueError("context.sensors: the sensor-angle criterion needs sensor "
                             "orientations")
        R_ts = sensor_rotations(context.sensors, m.num_sensors).to(theta.dtype)
        req = R_ts @ m.sensor_to_bone.to(theta.dtype)
        got = m.bone_orientations(theta)
        err = geodesic_angle(got, req.expand_as(got))
        if context.sensor_valid is not None:  # a dropped sample constrains nothing
            err = err * context.sensor_valid.to(err)
        return err


class RejectionProposal(Proposal):
    """Keep candidates of ``base`` whose every per-sensor error is ``<= threshold_deg``.

    Args:
        base: inner proposal (e.g. :class:`~torchmocap.proposals.base.GaussianDiffusionProposal`).
        criterion: ``(theta (K, D), context) -> (K, S)`` or ``(K,)`` errors in radians (e.g.
            :class:`SensorAngleCriterion`), or a :class:`~torchmocap.ik.SensorManifold` (then
            :class:`SensorAngleCriterion` of it), or a criterion answering pass/fail with a bool
            tensor (e.g. :class:`~torchmocap.proposals.spatial.PoseInSilhouette`; a candidate
            passes when all its entries are True).
        threshold_deg: acceptance threshold per sensor (degrees).
        max_tries: cap on the total number of candidates per call.
        max_rounds: cap on the number of batches per call.
        max_seconds: optional wall-clock cap per call.
        batch_size: largest batch of candidates drawn at once.
    """

    def __init__(
        self,
        base: Proposal,
        criterion: ErrorFn | SensorManifold,
        threshold_deg: float = 10.0,
        max_tries: int = 1_000_000,
        max_rounds: int = 10_000,
        max_seconds: float | None = None,
        batch_size: int = 20_000,
    ) -> None:
        super().__init__()
        if not threshold_deg > 0:
            raise ValueError(f"threshold_deg: expected a value > 0, got {threshold_deg}")
        for name, v in (("max_tries", max_tries), ("max_rounds", max_rounds),
                        ("batch_size", batch_size)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {v!r}")
        if not isinstance(base, Proposal):
            raise TypeError(f"base: expected a Proposal, got {type(base).__name__}")
        self.base = base
        self.error_fn = (SensorAngleCriterion(criterion) if isinstance(criterion, SensorManifold)
                         else criterion)
        if not callable(self.error_fn):
            raise TypeError(f"criterion: expected a callable, got {type(criterion).__name__}")
        self.threshold = math.radians(threshold_deg)
        self.threshold_deg = threshold_deg
        self.max_tries = int(max_tries)
        self.max_rounds = int(max_rounds)
        self.max_seconds = max_seconds
        self.batch_size = int(batch_size)

    @property
    def requires(self) -> tuple[str, ...]:  # type: ignore[override]
        extra = tuple(getattr(self.error_fn, "requires", ()))
        return tuple(dict.fromkeys(tuple(self.base.requires) + extra))

    def coordinates(self, theta: torch.Tensor) -> torch.Tensor:
        return self.base.coordinates(theta)

    @property
    def coordinate_std(self) -> torch.Tensor | None:
        return self.base.coordinate_std

    def sample(
        self, context: ProposalContext, num: int, generator: torch.Generator | None = None
    ) -> Proposed:
        if not isinstance(num, int) or num < 1:
            raise ValueError(f"num: expected an int >= 1, got {num!r}")
        t0 = time.perf_counter()
        out = None
        filled = 0
        tries = accepted = rounds = 0
        per_sensor = None
        pool = pool_err = None  # best rejected candidates (smallest worst-sensor error)
        stopped = "filled"
        while filled < num:
            if tries >= self.max_tries:
                stopped = "max_tries"
                break
            if rounds >= self.max_rounds:
                stopped = "max_rounds"
                break
            if (self.max_seconds is not None and rounds > 0
                    and time.perf_counter() - t0 >= self.max_seconds):
                stopped = "max_seconds"
                break
            need = num - filled
            rate = (accepted + 1) / (tries + 2)  # smoothed running acceptance rate
            k = int(min(self.batch_size, self.max_tries - tries,
                        max(need, math.ceil(1.2 * need / rate))))
            cand = self.base.sample(context, k, generator).particles
            if out is None:
                out = cand.new_empty(num, cand.shape[-1])
            err = self.error_fn(cand, context)
            if err.dim() == 1:
                err = err[:, None]
            if err.dtype == torch.bool:  # a criterion that answers pass/fail per part
                ok_s = err
                worst = (~err).sum(-1).to(cand.dtype)
            else:
                ok_s = err <= self.threshold
                worst = err.max(-1).values
            acc = ok_s.all(-1)
            ps = ok_s.sum(0)
            per_sensor = ps if per_sensor is None else per_sensor + ps
            tries += k
            rounds += 1
            idx = acc.nonzero().squeeze(-1)
            n_acc = int(idx.numel())
            accepted += n_acc
            take = min(n_acc, need)
            if take:
                out[filled : filled + take] = cand[idx[:take]]
                filled += take
            if filled < num:  # keep the best rejected candidates for slots that stay empty
                rej = (~acc).nonzero().squeeze(-1)
                c, e = cand[rej], worst[rej]
                if pool is not None:
                    c, e = torch.cat([pool, c]), torch.cat([pool_err, e])
                keep = min(num - filled, e.numel())
                best = torch.topk(e, keep, largest=False).indices
                pool, pool_err = c[best], e[best]
        valid = torch.zeros(num, dtype=torch.bool,
                            device=out.device if out is not None else None)
        valid[:filled] = True
        if filled < num:
            if pool is None or pool.shape[0] < num - filled:
                raise RuntimeError("RejectionProposal: no candidates were drawn (max_seconds "
                                   "too small?)")
            out[filled:] = pool[: num - filled]
        stats = {
            "acceptance_rate": accepted / max(tries, 1),
            "rejections_per_sample": (tries - accepted) / num,
            "tries": tries,
            "accepted": accepted,
            "rounds": rounds,
            "filled": filled / num,
            "per_sensor_acceptance": per_sensor.double() / max(tries, 1)
            if per_sensor is not None else None,
            "seconds": time.perf_counter() - t0,
            "stopped": stopped,
        }
        return Proposed(particles=out, valid=valid, stats=stats)

    def extra_repr(self) -> str:
        return f"threshold_deg={self.threshold_deg}, max_tries={self.max_tries}"
