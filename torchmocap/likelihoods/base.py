"""The likelihood interface: energy terms of poses given one frame's observations.

Convention (one for the whole library): a likelihood term returns an **energy**
``V = −log p(z | θ) + const`` per particle, shape ``(P,)``, lower is better. Annealing weights
particles by ``exp(−β V)``, a local optimiser descends ``V``, an SIR filter uses ``−V`` as the log
likelihood.

A term is an ``nn.Module`` with

- ``requires``: the observation modalities it reads (``"silhouettes"``, ``"images"``, ``"imu"``,
  ``"depth"``, ``"joints2d"``); a tracker refuses a sequence that lacks one;
- ``prepare(frame)``: per-frame preprocessing done once (sampled foreground pixels, colour
  planes, sensor rotations); the default returns the frame itself;
- ``energy(poses, observation) -> (P,)``: the energy of every particle, where ``poses`` is a
  :class:`Poses` — forward kinematics and capsule endpoints are computed once per evaluation and
  shared by all terms;
- ``evidence(observation) -> bool``: whether the frame holds usable evidence for the term (all
  views dropped, every sensor sample lost: no). Without evidence a term returns the same
  uninformative energy for every particle — never a "perfect" 0 — and the tracker reports the
  frame.

and declares its **capabilities**:

- ``differentiable``: whether the energy has gradients with respect to the poses (default yes; a
  0/1 coverage test has none), so that an inference that descends it (local descent, a
  mixture's local optimisation) can be refused a term it cannot use, naming it
  (``differentiable_hint`` says what to use instead);
- ``offers_gauss_newton(observation)`` and ``gauss_newton(poses, observation, hessian)``: an
  analytic energy, gradient and Gauss–Newton Hessian (default: none; 2D joints offer them),
  which a Levenberg–Marquardt inference uses instead of autograd.

:class:`WeightedSum` combines terms with weights from the config (``V = Σ_k w_k V_k``; a term of
weight 0 is neither evaluated nor required). :class:`FrameEnergy` binds a likelihood to one
prepared frame, giving the ``theta (P, D) -> (P,)`` callable that inference algorithms minimise.

Example:
    >>> from torchmocap.skeleton import human31
    >>> class Upright(Likelihood):            # a user's term: keep the spine straight
    ...     def energy(self, poses, observation):
    ...         return poses.kinematics.rotations[:, 1, 2, 2].neg() + 1
    >>> sk = human31()
    >>> V = FrameEnergy(Upright(), None, sk)
    >>> V(sk.zero_pose((5,))).shape
    torch.Size([5])
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import nn

__all__ = ["FrameEnergy", "Likelihood", "Poses", "WeightedSum", "blockwise", "check_block",
           "check_energy"]


class Poses:
    """A batch of poses ``theta (P, D)`` with lazily computed, cached kinematics.

    Args:
        theta: ``(P, D)`` poses of ``skeleton``.
        skeleton: the tracking model (:class:`~torchmocap.skeleton.Skeleton`).

    ``kinematics`` (global frames and positions) is computed on first use; ``endpoints(body)``
    gives the capsule axes ``(P, B, 2, 3)`` of a :class:`~torchmocap.body.CapsuleBody`, cached per
    body. Terms read these instead of running their own forward kinematics.
    """

    __slots__ = ("theta", "skeleton", "_kin", "_endpoints")

    def __init__(self, theta: torch.Tensor, skeleton) -> None:
        self.theta = theta
        self.skeleton = skeleton
        self._kin = None
        self._endpoints: dict[int, torch.Tensor] = {}

    @property
    def num(self) -> int:
        """Number of particles ``P``."""
        return int(self.theta.shape[0])

    @property
    def kinematics(self):
        """:class:`~torchmocap.skeleton.Kinematics` of ``theta`` (computed once)."""
        if self._kin is None:
            self._kin = self.skeleton(self.theta, check_finite=False)
        return self._kin

    def endpoints(self, body) -> torch.Tensor:
        """Capsule endpoints ``(P, B, 2, 3)`` of ``body`` at these poses (computed once)."""
        key = id(body)
        ep = self._endpoints.get(key)
        if ep is None:
            kin = (self.kinematics if body.skeleton is self.skeleton
                   else body.skeleton(self.theta, check_finite=False))
            ep = body.endpoints(kin)
            self._endpoints[key] = ep
        return ep


def blockwise(fn, x: torch.Tensor, block: int | None, *args: Any) -> torch.Tensor:
    """``fn(x, *args)`` of ``x (P, ...)`` evaluated block by block along dim 0 and concatenated:
    one call when ``block`` is None or ``P <= block``, else ``ceil(P / block)`` blocks of
    near-equal size (at most two sizes, so a compiled ``fn`` sees few shapes). Terms whose
    temporaries grow with ``P`` stay in the caches this way (the silhouette term at 4000
    particles: 3x faster in blocks of 512)."""
    P = x.shape[0]
    if block is None or P <= block:
        return fn(x, *args)
    return torch.cat([fn(part, *args) for part in x.tensor_split(-(-P // block))])


def check_block(block: Any) -> int | None:
    """``block`` (particles per block of a term's energy) checked: an int >= 1 or None."""
    if block is not None and (isinstance(block, bool) or not isinstance(block, int)
                              or block < 1):
        raise ValueError(f"block: expected an int >= 1 (particles per block) or null, got "
                         f"{block!r}")
    return block


def check_energy(v: Any, num: int, name: str) -> torch.Tensor:
    """Check that a term returned a ``(num,)`` float tensor without NaN (typed errors)."""
    if not isinstance(v, torch.Tensor) or v.shape != (num,):
        shape = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
        raise ValueError(f"{name}: expected an energy of shape ({num},), got {shape}")
    if bool(torch.isnan(v).any()):
        raise ValueError(f"{name}: returned NaN for {int(torch.isnan(v).sum())} of {num} "
                         "particles")
    return v


class Likelihood(nn.Module):
    """Base class of likelihood terms (see the module docstring for the contract).

    Subclasses set ``requires`` and implement :meth:`energy`; override :meth:`prepare` for
    per-frame preprocessing, and the capabilities (:attr:`differentiable`,
    :meth:`offers_gauss_newton` with :meth:`gauss_newton`) where they differ from the defaults.
    ``forward`` is :meth:`energy`.
    """

    requires: tuple[str, ...] = ()
    #: what to use instead when :attr:`differentiable` is False (for error messages)
    differentiable_hint: str = ""

    @property
    def differentiable(self) -> bool:
        """Whether the energy has gradients with respect to the poses (default: yes)."""
        return True

    def offers_gauss_newton(self, observation: Any) -> bool:
        """Whether :meth:`gauss_newton` gives this term's derivatives for ``observation``
        (default: no)."""
        return False

    def gauss_newton(self, poses: Poses, observation: Any, hessian: bool = True):
        """Energy ``(P,)``, analytic gradient ``(P, D)`` and Gauss–Newton Hessian
        ``(P, D, D)`` (None when ``hessian`` is False) of ``poses``; only where
        :meth:`offers_gauss_newton`."""
        raise NotImplementedError(f"{type(self).__name__} offers no Gauss-Newton derivatives")

    def prepare(self, frame: Any) -> Any:
        """Per-frame preprocessing of ``frame`` (a :class:`~torchmocap.data.Frame`); the result
        is passed to every :meth:`energy` call of that frame. Default: the frame itself."""
        return frame

    def energy(self, poses: Poses, observation: Any) -> torch.Tensor:
        """Energy ``(P,)`` of ``poses`` given the prepared ``observation``."""
        raise NotImplementedError(f"{type(self).__name__} must implement energy()")

    def evidence(self, observation: Any) -> bool:
        """Whether ``observation`` holds usable evidence for this term (default: yes)."""
        return True

    def forward(self, poses: Poses, observation: Any) -> torch.Tensor:
        return self.energy(poses, observation)

    def log_likelihood(self, poses: Poses, observation: Any) -> torch.Tensor:
        """``−energy``: the log-likelihood up to a constant."""
        return -self.energy(poses, observation)


class WeightedSum(Likelihood):
    """``V = Σ_k w_k V_k`` over named terms (Pons-Moll eq. 17: ``λ1 V_silh + λ2 V_app``).

    Args:
        terms: ``{name: Likelihood}``.
        weights: ``{name: weight}``; missing names weigh 1. A weight of 0 switches a term off
            (not evaluated, its modalities not required). Weights must be finite and ``>= 0``.
        optional: names of terms used only in frames that hold what they read (e.g. the
            silhouette term of a recording that may have no masks): their modalities are not
            required, and a frame without them is scored by the other terms.
    """

    def __init__(self, terms: Mapping[str, Likelihood], weights: Mapping[str, float] | None = None,
                 optional: Sequence[str] = ()) -> None:
        super().__init__()
        if not isinstance(terms, Mapping) or not terms:
            raise ValueError("terms: expected a non-empty mapping {name: Likelihood}")
        for name, t in terms.items():
            if not isinstance(t, Likelihood):
                raise TypeError(f"terms.{name}: expected a torchmocap Likelihood, got "
                                f"{type(t).__name__}")
        weights = dict(weights or {})
        unknown = sorted(set(weights) - set(terms))
        if unknown:
            raise ValueError(f"weights: no term named {unknown}; terms are {sorted(terms)}")
        w = {}
        for name in terms:
            v = weights.get(name, 1.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < 0:
                raise ValueError(f"weights.{name}: expected a finite number >= 0, got {v!r}")
            w[name] = float(v)
        if isinstance(optional, str) or not all(isinstance(k, str) for k in optional):
            raise ValueError(f"optional: expected a list of term names, got {optional!r}")
        stray = sorted(set(optional) - set(terms))
        if stray:
            raise ValueError(f"optional: no term named {stray}; terms are {sorted(terms)}")
        self.terms = nn.ModuleDict(dict(terms))
        self._weights = w
        self.optional = tuple(optional)

    @property
    def weights(self) -> dict[str, float]:
        """The weight of every term."""
        return dict(self._weights)

    def _weight(self, name: str) -> float:
        return self._weights[name]

    def active_terms(self) -> list[str]:
        """Names of the terms with a non-zero weight."""
        return [k for k in self.terms if self._weights[k] != 0]

    @property
    def requires(self) -> tuple[str, ...]:  # type: ignore[override]
        out: list[str] = []
        for k in self.active_terms():
            if k not in self.optional:
                out += [m for m in self.terms[k].requires if m not in out]
        return tuple(out)

    def prepare(self, frame: Any) -> dict[str, Any]:
        """Every active term's prepared observation (an optional term's only when the frame
        holds what it reads)."""
        return {k: self.terms[k].prepare(frame) for k in self.active_terms()
                if k not in self.optional
                or all(getattr(frame, m, None) is not None for m in self.terms[k].requires)}

    def present_terms(self, observation: Mapping[str, Any]) -> list[str]:
        """The active terms scoring this prepared frame (an optional term may be absent)."""
        return [k for k in self.active_terms() if k in observation]

    def evidence(self, observation: Mapping[str, Any]) -> bool:
        """True when at least one present term has evidence (see :meth:`missing_evidence`)."""
        return len(self.missing_evidence(observation)) < len(self.present_terms(observation))

    def missing_evidence(self, observation: Mapping[str, Any]) -> list[str]:
        """Names of the present terms without usable evidence in this frame."""
        return [k for k in self.present_terms(observation)
                if not self.terms[k].evidence(observation[k])]

    def term_energies(self, poses: Poses, observation: Mapping[str, Any]
                      ) -> dict[str, torch.Tensor]:
        """Unweighted energy ``(P,)`` of every present term."""
        return {k: check_energy(self.terms[k].energy(poses, observation[k]), poses.num,
                                f"terms.{k}")
                for k in self.present_terms(observation)}

    def energy(self, poses: Poses, observation: Mapping[str, Any]) -> torch.Tensor:
        total = None
        for k, v in self.term_energies(poses, observation).items():
            wv = v * self._weight(k)
            total = wv if total is None else total + wv
        return total

    @property
    def differentiable(self) -> bool:
        """Every active term is differentiable."""
        return all(self.terms[k].differentiable for k in self.active_terms())

    def offers_gauss_newton(self, observation: Mapping[str, Any]) -> bool:
        """Every term present in the frame offers Gauss–Newton derivatives."""
        present = self.present_terms(observation)
        return bool(present) and all(self.terms[k].offers_gauss_newton(observation[k])
                                     for k in present)

    def gauss_newton(self, poses: Poses, observation: Mapping[str, Any], hessian: bool = True):
        """The weighted sum of the present terms' Gauss–Newton derivatives."""
        tot = None
        for k in self.present_terms(observation):
            w = self._weight(k)
            v, g, H = self.terms[k].gauss_newton(poses, observation[k], hessian)
            part = (w * v, w * g, None if H is None else w * H)
            tot = part if tot is None else (tot[0] + part[0], tot[1] + part[1],
                                            None if H is None else tot[2] + part[2])
        return tot

    def extra_repr(self) -> str:
        return f"weights={self.weights}" + (f", optional={list(self.optional)}"
                                            if self.optional else "")


class FrameEnergy:
    """A likelihood bound to one frame: ``V(theta (P, D)) -> (P,)``.

    Args:
        likelihood: a :class:`Likelihood` (e.g. a :class:`WeightedSum`).
        observation: ``likelihood.prepare(frame)``.
        skeleton: the model the poses belong to (one forward kinematics per call, shared by all
            terms).
    """

    def __init__(self, likelihood: Likelihood, observation: Any, skeleton) -> None:
        self.likelihood = likelihood
        self.observation = observation
        self.skeleton = skeleton

    def __call__(self, theta: torch.Tensor) -> torch.Tensor:
        if theta.dim() != 2:
            raise ValueError(f"theta: expected shape (P, D), got {tuple(theta.shape)}")
        v = self.likelihood.energy(Poses(theta, self.skeleton), self.observation)
        return check_energy(v, theta.shape[0], f"likelihood {type(self.likelihood).__name__}")

    @property
    def differentiable(self) -> bool:
        """Whether the likelihood is differentiable (:attr:`Likelihood.differentiable`)."""
        return self.likelihood.differentiable

    @property
    def offers_gauss_newton(self) -> bool:
        """Whether :meth:`gauss_newton` is available for the bound frame."""
        return self.likelihood.offers_gauss_newton(self.observation)

    def gauss_newton(self, theta: torch.Tensor, hessian: bool = True):
        """``V (P,)``, ``grad (P, D)`` and the Gauss–Newton ``H (P, D, D)`` (None when
        ``hessian`` is False) of ``theta (P, D)``: the likelihood's analytic derivatives."""
        return self.likelihood.gauss_newton(Poses(theta, self.skeleton), self.observation,
                                            hessian)

    def missing_evidence(self) -> list[str]:
        """Terms (names) without usable evidence in the bound frame."""
        lik = self.likelihood
        if isinstance(lik, WeightedSum):
            return lik.missing_evidence(self.observation)
        return [] if lik.evidence(self.observation) else [type(lik).__name__]

    def terms(self, theta: torch.Tensor) -> dict[str, torch.Tensor]:
        """Per-term unweighted energies ``{name: (P,)}`` (a single term is named ``energy``)."""
        poses = Poses(theta, self.skeleton)
        if isinstance(self.likelihood, WeightedSum):
            return self.likelihood.term_energies(poses, self.observation)
        return {"energy": self.likelihood.energy(poses, self.observation)}
