"""Covariance-scaled (CSS) and spherical (SS) sampling around modes (Sminchisescu & Triggs 2003,
§4 and Table 1; Sminchisescu & Triggs 2001).

:class:`CovarianceScaledProposal` draws from the mixture ``sum_k pi_k N(mu_k, s Sigma_k)`` — or
its heavy-tailed (Student-t / Cauchy) version with the same scale matrices — where the modes
``mu_k`` are ``context.previous`` (``(K, D)`` or one ``(D,)``), the weights ``pi_k`` come from
``context.log_weights`` and ``Sigma_k`` is the inverse (Gauss–Newton) Hessian of the cost at each
mode, handed in through the context:

* ``context.covariances``: ``(K, D, D)`` or ``(D, D)`` covariances, else
* ``context.hessians``: ``(K, D, D)`` / ``(D, D)`` Hessians, inverted here
  (:func:`~torchmocap.distributions.hessian_to_covariance`, eigenvalues floored at
  ``1 / max_std^2``), else
* the proposal's own diagonal ``std`` (rotations ``std_deg``, translations
  ``translation_std``) — then CSS is plain Gaussian diffusion.

``spherical=True`` is SS: every ``Sigma_k`` is replaced by the isotropic covariance of equal
volume, ``R I`` with ``R = (lambda_1 ... lambda_n)^(1/n)`` (the paper's fair comparison).
Samples outside the joint limits are projected back onto them (``boundary``). The scale
``s`` is ``scale * context.scale``; an annealer's ``context.std`` replaces the covariance by
``diag(std^2)``. ``stats``: ``scale``, ``clamped`` (fraction of samples moved by the limits),
``components`` (K) and ``component`` — the ``(P,)`` int64 mode index of each sample, which
:class:`~torchmocap.proposals.KinematicJumpProposal` reads to vote a chain per mode.

``log_q`` is not reported (the projection onto the limits makes the density a mixture of a
continuous part and point masses on the boundary).

Example:
    >>> from torchmocap.skeleton import human31
    >>> from torchmocap.proposals import ProposalContext
    >>> sk = human31()
    >>> css = CovarianceScaledProposal(sk, scale=8.0)
    >>> ctx = ProposalContext(previous=sk.zero_pose(), covariances=torch.eye(31))
    >>> css.sample(ctx, 10, torch.Generator().manual_seed(0)).particles.shape
    torch.Size([10, 31])
"""

from __future__ import annotations

import math

import torch

from torchmocap.distributions.covariance_scaled import (
    _TAILS,
    _check_tails,
    _sqrt_factor,
    _tail_scale,
    hessian_to_covariance,
    spherical_covariance,
)
from torchmocap.proposals.base import Proposal, ProposalContext, Proposed, as_std
from torchmocap.proposals.bounds import BOUNDARIES, bound_particles

__all__ = ["CovarianceScaledProposal", "context_covariances", "mode_set"]


def mode_set(context: ProposalContext, num_dofs: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(K, D)`` modes and their ``(K,)`` normalised weights (float64) from a context
    (``previous`` ``(D,)`` or ``(K, D)``; ``log_weights`` or uniform)."""
    prev = context.previous
    if not isinstance(prev, torch.Tensor) or prev.dim() not in (1, 2) \
            or prev.shape[-1] != num_dofs:
        shape = tuple(prev.shape) if isinstance(prev, torch.Tensor) else type(prev).__name__
        raise ValueError(f"context.previous: expected ({num_dofs},) or (K, {num_dofs}), got "
                         f"{shape}")
    if not bool(torch.isfinite(prev).all()):
        raise ValueError("context.previous: expected finite values, found NaN or inf")
    modes = prev[None] if prev.dim() == 1 else prev
    K = modes.shape[0]
    if context.log_weights is None:
        w = torch.full((K,), 1.0 / K, dtype=torch.float64, device=modes.device)
    else:
        lw = torch.as_tensor(context.log_weights)
        if lw.shape != (K,):
            raise ValueError(f"context.log_weights: expected ({K},), got {tuple(lw.shape)}")
        w = torch.softmax(lw.double().to(modes.device), 0)
        if not bool(torch.isfinite(w).all()):
            raise ValueError("context.log_weights: expected finite log weights")
    return modes, w


def context_covariances(context: ProposalContext, K: int, num_dofs: int, like: torch.Tensor,
                        max_std: float | None = None) -> torch.Tensor | None:
    """``(K, D, D)`` covariances of the modes from the context (``covariances``, else
    ``hessians``), or None when the context has neither."""
    D = num_dofs
    for key in ("covariances", "hessians"):
        m = getattr(context, key)
        if m is None:
            continue
        m = torch.as_tensor(m).to(dtype=like.dtype, device=like.device)
        if m.shape == (D, D):
            m = m.expand(K, D, D)
        if m.shape != (K, D, D):
            raise ValueError(f"context.{key}: expected ({D}, {D}) or ({K}, {D}, {D}), "
                             f"got {tuple(m.shape)}")
        if not bool(torch.isfinite(m).all()):
            raise ValueError(f"context.{key}: expected finite values")
        if key == "hessians":
            floor = 0.0 if max_std is None else 1.0 / max_std**2
            m = hessian_to_covariance(m, floor=floor)
        return m
    return None


class CovarianceScaledProposal(Proposal):
    """CSS / SS draws around the modes of ``context.previous`` (module docstring).

    Args:
        skeleton: the tracking model (runtime dependency): its joint limits and DoF count;
            optional when ``num_dofs`` (and ``lower``/``upper``) are given.
        scale: ``s`` (covariance factor; the paper's 1, 4, 8, 16).
        tails: ``"gaussian"``, ``"student_t"`` (needs ``dof``) or ``"cauchy"`` (HT).
        dof: Student-t degrees of freedom.
        spherical: SS — isotropic covariance of the same volume as each ``Sigma_k``.
        std_deg, translation_std: the own diagonal std (rotations in degrees, root translation
            in metres) used when the context brings no covariance.
        max_std: eigenvalue floor ``1 / max_std^2`` when inverting ``context.hessians``.
        boundary: ``"clamp"`` (project onto the limits), ``"reflect"`` or ``"none"``.
        uniform_mix: fraction ``u`` of samples whose mode is drawn uniformly (the mode
            probabilities are ``(1 - u) pi_k + u / K``), so low-weight modes are explored.
        num_dofs, lower, upper: the DoF count and limits without a skeleton.
    """

    def __init__(self, skeleton=None, scale: float = 4.0, tails: str = "gaussian",
                 dof: float | None = None, spherical: bool = False, std_deg: float = 3.0,
                 translation_std: float = 0.02, max_std: float | None = None,
                 boundary: str = "clamp", uniform_mix: float = 0.0,
                 num_dofs: int | None = None, lower=None, upper=None) -> None:
        super().__init__()
        if not (isinstance(scale, (int, float)) and not isinstance(scale, bool)
                and math.isfinite(scale) and scale > 0):
            raise ValueError(f"scale: expected a finite number > 0, got {scale!r}")
        if tails not in _TAILS:
            raise ValueError(f"tails: expected one of {_TAILS}, got {tails!r}")
        _check_tails(tails, dof)
        if boundary not in BOUNDARIES:
            raise ValueError(f"boundary: expected one of {BOUNDARIES}, got {boundary!r}")
        if not (isinstance(uniform_mix, (int, float)) and 0 <= uniform_mix <= 1):
            raise ValueError(f"uniform_mix: expected a number in [0, 1], got {uniform_mix!r}")
        if max_std is not None and not (math.isfinite(max_std) and max_std > 0):
            raise ValueError(f"max_std: expected a finite number > 0 or None, got {max_std!r}")
        if skeleton is not None:
            from torchmocap.proposals.base import skeleton_std

            num_dofs = skeleton.num_dofs
            std = skeleton_std(skeleton, std_deg, translation_std)
            lower = skeleton.lower if lower is None else lower
            upper = skeleton.upper if upper is None else upper
        else:
            if num_dofs is None:
                raise ValueError("num_dofs: required without a skeleton")
            std = as_std(math.radians(std_deg), int(num_dofs), "std_deg")
        self.num_dofs = int(num_dofs)
        self.scale = float(scale)
        self.tails, self.dof = tails, dof
        self.spherical = bool(spherical)
        self.boundary = boundary
        self.uniform_mix = float(uniform_mix)
        self.max_std = max_std
        self.register_buffer("std", std.float())
        self.register_buffer("lower", None if lower is None else
                             torch.as_tensor(lower).detach().float().clone())
        self.register_buffer("upper", None if upper is None else
                             torch.as_tensor(upper).detach().float().clone())

    @property
    def coordinate_std(self) -> torch.Tensor:
        return self.std

    def covariances(self, context: ProposalContext, K: int, like: torch.Tensor) -> torch.Tensor:
        """``(K, D, D)`` covariances ``Sigma_k`` this draw uses (before ``spherical``)."""
        D = self.num_dofs
        if context.std is not None:
            s = torch.as_tensor(context.std, dtype=like.dtype, device=like.device)
            if s.shape != (D,):
                raise ValueError(f"context.std: expected ({D},), got {tuple(s.shape)}")
            return torch.diag_embed(s * s).expand(K, D, D)
        cov = context_covariances(context, K, D, like, self.max_std)
        if cov is None:
            s = self.std.to(like)
            cov = torch.diag_embed(s * s).expand(K, D, D)
        return cov

    def sample(self, context: ProposalContext, num: int,
               generator: torch.Generator | None = None) -> Proposed:
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            raise ValueError(f"num: expected an int >= 1, got {num!r}")
        modes, w = mode_set(context, self.num_dofs)
        K, D = modes.shape
        dt, dev = modes.dtype, modes.device
        cov = self.covariances(context, K, modes)
        if self.spherical:
            cov = spherical_covariance(cov + 1e-12 * torch.eye(D, dtype=dt, device=dev))
        cscale = float(context.scale) if context.std is None else 1.0
        if not (math.isfinite(cscale) and cscale >= 0):
            raise ValueError(f"context.scale: expected a finite number >= 0, got "
                             f"{context.scale!r}")
        s = self.scale * cscale
        probs = (1 - self.uniform_mix) * w + self.uniform_mix / K
        comp = torch.multinomial(probs, num, replacement=True, generator=generator).to(dev)
        A = _sqrt_factor(0.5 * (cov + cov.transpose(-1, -2)), "covariances")  # (K, D, D)
        z = torch.randn(num, D, generator=generator, dtype=dt, device=dev)
        y = (A[comp] @ z[..., None])[..., 0] * math.sqrt(s)
        tail = _tail_scale(self.tails, self.dof, (num,), generator, dt, dev)
        if tail is not None:
            y = y * tail[:, None]
        raw = modes[comp] + y
        theta = raw
        if self.boundary != "none" and (self.lower is not None or self.upper is not None):
            theta = bound_particles(raw, None if self.lower is None else self.lower.to(raw),
                                    None if self.upper is None else self.upper.to(raw),
                                    self.boundary)
        moved = (theta != raw).any(-1)
        stats = {"scale": s, "components": K, "clamped": float(moved.double().mean()),
                 "component": comp}
        return Proposed(particles=theta, stats=stats)

    def extra_repr(self) -> str:
        return (f"num_dofs={self.num_dofs}, scale={self.scale}, tails={self.tails!r}, "
                f"spherical={self.spherical}, boundary={self.boundary!r}, "
                f"uniform_mix={self.uniform_mix}")
