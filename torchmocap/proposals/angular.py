"""The angular prior of Hauberg & Pedersen (2011, eq. 3) as a proposal with a proper density.

``p(θ_t | θ_{t−1}) ∝ N(θ_t | θ_{t−1}, diag(σ²)) U_Θ(θ_t)``: per DoF a Gaussian around the
ancestor *truncated* to the joint limits, normaliser included
(:class:`~torchmocap.distributions.TruncatedNormal`) — not a clamp, which would pile the mass
outside the limits onto them. ``log_q`` is the density of the draw; ``log_prior`` the density of
the same value under the prior this proposal approximates (``prior_scale`` times its own std;
``prior_scale = 1``: the proposal *is* the prior and the SIR correction factor is 1).

Only the DoFs of the ``joints`` being tracked move (e.g. the upper body of the paper's
experiments: spine, neck, shoulders, elbows, wrists); every other DoF keeps its ancestor's value
and does not enter the densities. Shapes: ``P`` particles, ``D`` DoF.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from torchmocap.distributions.truncated_normal import TruncatedNormal
from torchmocap.geometry import wrap_angle
from torchmocap.proposals.base import (
    Proposal,
    ProposalContext,
    Proposed,
    context_std,
    select_ancestors,
    skeleton_std,
)

__all__ = ["UPPER_BODY", "AngularPriorProposal", "free_dofs"]

#: The tracked joints of Hauberg & Pedersen's upper-body experiments: the pelvis (root) and the
#: legs stay fixed; the spine is tracked too (a standing person still bends and turns the torso a
#: little — 13-14 deg in the arm clips of the reproduction).
UPPER_BODY = ("spine", "neck", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow",
              "r_wrist")


def free_dofs(skeleton, joints: str | Sequence[str] | None) -> torch.Tensor:
    """``(K,)`` indices of the DoFs of ``joints`` (``None``/``"all"``: every DoF;
    ``"upper_body"``: :data:`UPPER_BODY`, those the skeleton has)."""
    if joints is None or joints == "all":
        return torch.arange(skeleton.num_dofs)
    if joints == "upper_body":
        joints = [j for j in UPPER_BODY if j in skeleton.joint_names]
    if isinstance(joints, str):
        raise ValueError(f"joints: expected 'all', 'upper_body' or a list of joint names, got "
                         f"{joints!r}")
    idx: list[int] = []
    for j in joints:
        if j not in skeleton.joint_names:
            raise ValueError(f"joints: unknown joint {j!r}; known: {list(skeleton.joint_names)}")
        idx += skeleton.joint_dofs(j)
    if not idx:
        raise ValueError(f"joints: {list(joints)} have no degrees of freedom")
    return torch.tensor(sorted(set(idx)))


class AngularPriorProposal(Proposal):
    """Truncated Gaussian diffusion of the tracked DoFs around each ancestor (eq. 3).

    Args:
        skeleton: the model (limits; rotation vs translation DoFs).
        rotation_std_deg, translation_std: per-DoF std (degrees / metres).
        joints: the tracked joints (``"all"``, ``"upper_body"`` or names); the rest stay put.
        prior_scale: the prior's std relative to this proposal's (``log_prior`` is evaluated
            with it; 1 = the proposal is the prior).
        speed_gain: widens each DoF's std to ``sqrt(σ² + (g · |Δθ|)²)``, ``Δθ`` the DoF's
            change between the tracker's last two estimates (``context.history``;
            angles along the shorter arc) — the angular counterpart of
            :class:`~torchmocap.proposals.SpatialPriorProposal`'s ``speed_gain``; the prior of
            ``log_prior`` widens with it. 0 (default): the fixed spread of eq. 3.
    """

    def __init__(self, skeleton, rotation_std_deg: float = 5.0, translation_std: float = 0.02,
                 joints: str | Sequence[str] | None = "all", prior_scale: float = 1.0,
                 speed_gain: float = 0.0) -> None:
        super().__init__()
        for name, v in (("rotation_std_deg", rotation_std_deg),
                        ("translation_std", translation_std), ("prior_scale", prior_scale)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v <= 0:
                raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
        if isinstance(speed_gain, bool) or not isinstance(speed_gain, (int, float)) \
                or not math.isfinite(speed_gain) or speed_gain < 0:
            raise ValueError(f"speed_gain: expected a finite number >= 0, got {speed_gain!r}")
        self.speed_gain = float(speed_gain)
        self.num_dofs = skeleton.num_dofs
        self.prior_scale = float(prior_scale)
        self.register_buffer("rotational", skeleton.rotation_mask().cpu())
        self.register_buffer("free", free_dofs(skeleton, joints))
        std = skeleton_std(skeleton, rotation_std_deg, translation_std)
        self.register_buffer("std", std[self.free].clone())
        self.register_buffer("lower", skeleton.lower[self.free].detach().clone())
        self.register_buffer("upper", skeleton.upper[self.free].detach().clone())

    def coordinates(self, theta: torch.Tensor) -> torch.Tensor:
        return theta.index_select(-1, self.free.to(theta.device))

    @property
    def coordinate_std(self) -> torch.Tensor:
        return self.std

    def _dist(self, loc: torch.Tensor, std: torch.Tensor) -> TruncatedNormal:
        lo, hi = self.lower.to(loc), self.upper.to(loc)
        # an ancestor a hair outside its limits (rounding) must not break the window
        loc = torch.maximum(torch.minimum(loc, hi), lo)
        return TruncatedNormal(loc, std.clamp_min(1e-12).expand_as(loc), lo.expand_as(loc),
                               hi.expand_as(loc), validate_args=False)

    def _spread(self, context: ProposalContext) -> torch.Tensor:
        """Per-DoF std ``(d,)`` of the tracked DoFs: ``std``, widened by ``speed_gain`` times
        each DoF's change between the last two estimates when the tracker passes them."""
        history = context.history
        if self.speed_gain == 0 or history is None or history.shape[0] < 2:
            return self.std
        delta = (history[-1] - history[-2]).to(self.std)
        rot = self.rotational.to(delta.device)
        delta = torch.where(rot, wrap_angle(delta), delta)
        d = self.coordinates(delta).abs() * self.speed_gain
        return torch.sqrt(self.std.square() + d.square())

    def sample(self, context: ProposalContext, num: int,
               generator: torch.Generator | None = None) -> Proposed:
        base = select_ancestors(context, num, self.num_dofs, generator)
        loc = self.coordinates(base)
        own = self._spread(context)
        std = context_std(context, own, loc)
        q = self._dist(loc, std)
        x = q.sample(generator=generator)
        theta = base.clone()
        theta[:, self.free.to(theta.device)] = x
        log_q = q.log_prob(x).sum(-1)
        prior = self._dist(loc, own.to(loc) * self.prior_scale)
        log_prior = prior.log_prob(x).sum(-1)
        return Proposed(particles=theta, log_q=log_q, log_prior=log_prior)

    def extra_repr(self) -> str:
        return (f"free_dofs={self.free.numel()}, prior_scale={self.prior_scale}, "
                f"speed_gain={self.speed_gain}")
