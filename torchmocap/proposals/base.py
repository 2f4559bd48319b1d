"""The proposal interface: ``sample(context, num, generator) -> Proposed``.

A proposal draws ``P`` candidate poses ``theta (P, D)`` given a :class:`ProposalContext` (the
previous particles or estimate, this frame's observations such as sensor orientations). It
returns a :class:`Proposed` with the particles, ``log_q`` when the proposal density is known
(so that an SIR filter can form its correction factor), a per-particle ``valid`` flag when some
slots could not be filled as asked (e.g. a capped rejection sampler), and a ``stats`` dict
(acceptance rates, tries, residuals, timings).

Proposals are also the mutation kernels of annealing: an inference algorithm may set
``context.std`` (a per-coordinate std replacing the proposal's own) or ``context.scale`` (a factor
on it) in the proposal's own **coordinates** — ``proposal.coordinates(theta)``: the full pose for
:class:`GaussianDiffusionProposal`, the active coordinates for a manifold proposal — so an
annealer can measure the particle spread in the space the proposal perturbs.

``requires`` names the observation modalities a proposal reads (e.g. ``("imu",)``).

:class:`GaussianDiffusionProposal` is the simplest concrete proposal — per-DoF Gaussian
diffusion of the previous particles in the full pose space (the G/GS trackers' mutation, and
the inner sampler of the rejection-sampling baseline of Pons-Moll et al. 2010, Fig. 9b).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from torchmocap.proposals.bounds import BOUNDARIES, bound_particles

__all__ = [
    "PreviousFrame",
    "Proposal",
    "ProposalContext",
    "Proposed",
    "GaussianDiffusionProposal",
    "select_ancestors",
    "as_std",
]


@dataclass
class PreviousFrame:
    """What a frame's inference and proposal may use of the frames before it (the tracker's
    state between frames; ``None`` fields where the tracker has none yet).

    Attributes:
        estimate: ``(D,)`` the previous frame's estimate.
        history: ``(H, D)`` the last ``H <= 3`` estimates, oldest first.
        particles: ``(P, D)`` the previous frame's final particle set.
        log_weights: ``(P,)`` its normalised log weights.
        carry: whatever the inference kept for the next frame
            (:attr:`~torchmocap.filters.InferenceResult.carry`, e.g. a mixture's components).
    """

    estimate: torch.Tensor | None = None
    history: torch.Tensor | None = None
    particles: torch.Tensor | None = None
    log_weights: torch.Tensor | None = None
    carry: Any = None


@dataclass
class ProposalContext:
    """What a proposal may condition on.

    Attributes:
        previous: ``(P0, D)`` previous particles or ``(D,)`` previous estimate / prediction.
        log_weights: optional ``(P0,)`` log weights of ``previous`` (ancestors are drawn from
            them when ``P0 != num``; uniform otherwise).
        sensors: optional ``(S, 3, 3)`` / ``(S, 4)`` tracking-sensor orientations of this frame
            (or per particle ``(P, S, ...)``).
        sensor_valid: optional ``(S,)`` bool, False for dropped sensor samples.
        frame: this frame's observations (a :class:`~torchmocap.data.Frame` restricted to what
            the tracker may see), for data-driven proposals.
        std: optional per-coordinate std ``(d,)`` replacing the proposal's own diffusion std
            (set per annealing layer).
        scale: factor on the proposal's own std (ignored when ``std`` is given).
        previous_frame: the tracker's state from the frames before (:class:`PreviousFrame`),
            None outside a tracker or on the first frame.
        covariances: optional ``(K, D, D)`` (or ``(D, D)``) covariances of the ``previous``
            modes (covariance-scaled sampling, kinematic jumps).
        hessians: optional ``(K, D, D)`` / ``(D, D)`` Hessians of the energy at the modes
            (inverted into covariances where no ``covariances`` are given).
    """

    previous: torch.Tensor
    log_weights: torch.Tensor | None = None
    sensors: torch.Tensor | None = None
    sensor_valid: torch.Tensor | None = None
    frame: Any = None
    std: torch.Tensor | None = None
    scale: float = 1.0
    previous_frame: PreviousFrame | None = None
    covariances: torch.Tensor | None = None
    hessians: torch.Tensor | None = None

    @property
    def last_estimate(self) -> torch.Tensor | None:
        """``(D,)`` the previous frame's estimate, when the tracker passed one."""
        return None if self.previous_frame is None else self.previous_frame.estimate

    @property
    def history(self) -> torch.Tensor | None:
        """``(H, D)`` the tracker's last estimates, oldest first, when it passed them."""
        return None if self.previous_frame is None else self.previous_frame.history


@dataclass
class Proposed:
    """Output of :meth:`Proposal.sample`.

    Attributes:
        particles: ``(P, D)`` proposed poses.
        log_q: ``(P,)`` log proposal density, when known.
        log_prior: ``(P,)`` log prior density, when known.
        valid: ``(P,)`` bool, False for slots that do not satisfy the proposal's constraint
            (e.g. a rejection sampler out of tries returns its best candidate there).
        stats: diagnostics (floats/ints/tensors), e.g. ``acceptance_rate``, ``tries``.
    """

    particles: torch.Tensor
    log_q: torch.Tensor | None = None
    log_prior: torch.Tensor | None = None
    valid: torch.Tensor | None = None
    stats: dict[str, Any] = field(default_factory=dict)


class Proposal(nn.Module):
    """Base class: subclasses implement :meth:`sample`; ``forward`` calls it.

    Override :meth:`coordinates` (and :attr:`coordinate_std`) when the proposal perturbs
    something other than the full pose vector, and set ``requires`` to the modalities it reads.
    """

    requires: tuple[str, ...] = ()

    def sample(
        self, context: ProposalContext, num: int, generator: torch.Generator | None = None
    ) -> Proposed:
        raise NotImplementedError(f"{type(self).__name__} must implement sample()")

    def forward(
        self, context: ProposalContext, num: int, generator: torch.Generator | None = None
    ) -> Proposed:
        return self.sample(context, num, generator)

    def coordinates(self, theta: torch.Tensor) -> torch.Tensor:
        """The coordinates ``(..., d)`` this proposal perturbs (default: the pose itself)."""
        return theta

    @property
    def coordinate_std(self) -> torch.Tensor | None:
        """The proposal's own diffusion std in :meth:`coordinates` units ``(d,)``, if any."""
        return None


def _check_num(num: int) -> None:
    if not isinstance(num, int) or isinstance(num, bool) or num < 1:
        raise ValueError(f"num: expected an int >= 1, got {num!r}")


def select_ancestors(
    context: ProposalContext, num: int, num_dofs: int, generator: torch.Generator | None = None
) -> torch.Tensor:
    """``(num, D)`` starting poses: the estimate repeated, the particles themselves when
    ``P0 == num`` (and no weights), or ancestors drawn by weight / uniformly otherwise."""
    _check_num(num)
    prev = context.previous
    if not isinstance(prev, torch.Tensor) or prev.shape[-1:] != (num_dofs,) or prev.dim() > 2:
        shape = tuple(prev.shape) if isinstance(prev, torch.Tensor) else type(prev).__name__
        raise ValueError(f"context.previous: expected (P0, {num_dofs}) or ({num_dofs},), "
                         f"got {shape}")
    if not bool(torch.isfinite(prev).all()):
        raise ValueError("context.previous: expected finite values, found NaN or inf")
    if prev.dim() == 1:
        return prev.expand(num, num_dofs)
    p0 = prev.shape[0]
    if context.log_weights is None:
        if p0 == num:
            return prev
        idx = torch.randint(p0, (num,), generator=generator, device=prev.device)
        return prev[idx]
    lw = context.log_weights
    if lw.shape != (p0,):
        raise ValueError(f"context.log_weights: expected ({p0},), got {tuple(lw.shape)}")
    w = torch.softmax(lw.double(), 0)
    idx = torch.multinomial(w, num, replacement=True, generator=generator)
    return prev[idx.to(prev.device)]


def as_std(std: float | Sequence[float] | torch.Tensor, n: int, name: str) -> torch.Tensor:
    """A ``(n,)`` float tensor of non-negative finite standard deviations."""
    t = torch.as_tensor(std, dtype=torch.float32).flatten()
    if t.numel() == 1:
        t = t.expand(n).clone()
    if t.shape != (n,):
        raise ValueError(f"{name}: expected a scalar or ({n},) std, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise ValueError(f"{name}: expected finite values >= 0")
    return t


def context_std(context: ProposalContext, own: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """The std to use for a draw: ``context.std`` when set, else ``own * context.scale``, as a
    ``(d,)`` or ``(P, d)`` tensor in ``like``'s dtype/device (typed errors on a bad shape)."""
    d = own.shape[-1]
    if context.std is not None:
        s = torch.as_tensor(context.std, dtype=like.dtype, device=like.device)
        if s.shape[-1:] != (d,) or s.dim() > 2:
            raise ValueError(f"context.std: expected ({d},) or (P, {d}), got {tuple(s.shape)}")
        return s
    scale = float(context.scale)
    if not (math.isfinite(scale) and scale >= 0):
        raise ValueError(f"context.scale: expected a finite number >= 0, got {context.scale!r}")
    return own.to(dtype=like.dtype, device=like.device) * scale


class GaussianDiffusionProposal(Proposal):
    """``theta = ancestor + N(0, diag(std^2))`` in the full pose space, projected onto limits.

    Args:
        std: scalar or ``(D,)`` per-DoF standard deviation (radians; metres for translations).
        num_dofs: ``D`` (needed when ``std`` is a scalar).
        lower, upper: optional ``(D,)`` limits.
        boundary: how samples outside the limits are brought back: ``"clamp"``, ``"reflect"``
            or ``"none"``. ``log_q`` (the Gaussian density around the ancestor) is reported only
            without limits.

    :meth:`from_skeleton` builds it from a skeleton (rotation and translation stds, the
    skeleton's limits) — what the ``proposal/gaussian_diffusion`` config does.
    """

    def __init__(
        self,
        std: float | Sequence[float] | torch.Tensor,
        num_dofs: int | None = None,
        lower: torch.Tensor | None = None,
        upper: torch.Tensor | None = None,
        boundary: str = "clamp",
    ) -> None:
        super().__init__()
        if num_dofs is None:
            num_dofs = int(torch.as_tensor(std).numel())
        if boundary not in BOUNDARIES:
            raise ValueError(f"boundary: expected one of {BOUNDARIES}, got {boundary!r}")
        self.num_dofs = int(num_dofs)
        self.boundary = boundary
        self.register_buffer("std", as_std(std, self.num_dofs, "std"))
        self.register_buffer("lower", None if lower is None else lower.detach().float().clone())
        self.register_buffer("upper", None if upper is None else upper.detach().float().clone())

    @classmethod
    def from_skeleton(cls, skeleton, rotation_std_deg: float = 3.0, translation_std: float = 0.02,
                      limits: bool = True, boundary: str = "clamp") -> GaussianDiffusionProposal:
        """Per-DoF std ``rotation_std_deg`` (degrees) on rotations and ``translation_std``
        (metres) on translations of ``skeleton``; its joint limits when ``limits``."""
        for name, v in (("rotation_std_deg", rotation_std_deg),
                        ("translation_std", translation_std)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
        std = skeleton_std(skeleton, rotation_std_deg, translation_std)
        return cls(std, skeleton.num_dofs,
                   skeleton.lower if limits else None, skeleton.upper if limits else None,
                   boundary)

    @property
    def coordinate_std(self) -> torch.Tensor:
        return self.std

    def sample(
        self, context: ProposalContext, num: int, generator: torch.Generator | None = None
    ) -> Proposed:
        base = select_ancestors(context, num, self.num_dofs, generator)
        std = context_std(context, self.std, base)
        eps = torch.randn(num, self.num_dofs, generator=generator, dtype=base.dtype,
                          device=base.device)
        theta = base + eps * std
        log_q = None
        if (self.lower is not None or self.upper is not None) and self.boundary != "none":
            lo = self.lower.to(base.dtype) if self.lower is not None else None
            hi = self.upper.to(base.dtype) if self.upper is not None else None
            theta = bound_particles(theta, lo, hi, self.boundary)
        elif std.dim() == 1:
            pos = std > 0
            z = eps[:, pos]
            log_q = (-0.5 * (z * z).sum(-1) - torch.log(std[pos]).sum()
                     - 0.5 * math.log(2 * math.pi) * int(pos.sum()))
        return Proposed(particles=theta, log_q=log_q)

    def extra_repr(self) -> str:
        return f"num_dofs={self.num_dofs}, boundary={self.boundary!r}"


def skeleton_std(skeleton, rotation_std_deg: float, translation_std: float) -> torch.Tensor:
    """``(D,)`` per-DoF std of ``skeleton``: radians on rotations, metres on translations."""
    std = torch.full((skeleton.num_dofs,), math.radians(rotation_std_deg), dtype=torch.float32)
    std[list(skeleton.translation_dofs)] = float(translation_std)
    return std
