"""Offline smoothing of a multi-hypothesis track: the most probable sequence of kept modes.

A multi-hypothesis filter (:class:`~torchmocap.filters.MixtureInference`, the Sminchisescu &
Triggs tracker) keeps ``K`` modes per frame — under monocular depth ambiguity often the
mirror-image interpretations of the same image, which tie on the likelihood. Its per-frame
estimate must choose among them from the past alone (:class:`~torchmocap.filters.
TemporalMapEstimator`: the mode closest to the prediction); once it follows the wrong branch it
has no reason to come back. With the whole clip recorded, the choice can use the future too:
:class:`ViterbiSmoother` returns the mode sequence ``k_1 .. k_T`` maximising::

    sum_t  e_t(k_t)  +  sum_t  log N(theta_t[k_t]; theta_{t-1}[k_{t-1}], diag sigma^2)

— the MAP trajectory of a hidden Markov model whose states are the kept modes, with emission
``e_t(k) = -V_t(theta_t[k])`` (the mode's energy: negative log-likelihood; or its filter weight
``log w_t(k)``, which already holds the filter's prior) and the constant-position Gaussian
transition of :class:`~torchmocap.filters.TemporalMapEstimator` (rotation differences wrapped to
``(-pi, pi]``). Exact dynamic programming (Viterbi), ``O(T K^2 D)``. Frame 0 is the known initial
pose. This is a fixed-interval smoother: it sees the future, so compare it with other smoothers,
not with filters (the trackers' ``Track.filtered`` keeps the filtered estimates).

Functional core: :func:`viterbi_path`; module:
:class:`ViterbiSmoother` (``tracker.smoother``; Hydra: ``+smoother@tracker.smoother=viterbi``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

from torchmocap.filters.optim.temporal_prior import TemporalPrior, check_prior_stds
from torchmocap.filters.smoothing.base import Smoother

__all__ = ["ViterbiSmoother", "viterbi_path"]

EMISSIONS = ("energy", "weights")


def viterbi_path(emissions: Sequence[torch.Tensor], transition) -> tuple[list[int], float]:
    """Exact MAP state sequence of a chain with a varying number of states per step.

    Args:
        emissions: ``T`` tensors ``(K_t,)`` of log emission scores (``K_t >= 1``, finite).
        transition: ``transition(t) -> (K_{t-1}, K_t)`` log transition scores into step ``t``
            (``t >= 1``).

    Returns:
        ``(path, score)``: the state index per step and the path's total log score. Ties go to
        the lowest index.
    """
    if not emissions:
        raise ValueError("emissions: expected at least one step")
    delta = emissions[0].to(torch.float64)
    back = []
    for t in range(1, len(emissions)):
        s = delta[:, None] + transition(t).to(torch.float64)  # (K_{t-1}, K_t)
        best, arg = s.max(0)
        back.append(arg)
        delta = best + emissions[t].to(torch.float64)
    k = int(torch.argmax(delta))
    score = float(delta[k])
    path = [k]
    for arg in reversed(back):
        k = int(arg[k])
        path.append(k)
    return path[::-1], score


class ViterbiSmoother(Smoother):
    """The most probable sequence of the hypotheses a multi-hypothesis tracker kept per frame.

    Args:
        skeleton: the tracking model (its translation DoFs get ``translation_std``).
        rotation_std_deg: ``σ`` of every rotation DoF's change per frame (degrees).
        translation_std: ``σ`` of the root translation's change per frame (metres).
        emission: ``"energy"`` (``-V`` of each mode: the likelihood alone, the transition being
            the only temporal term) or ``"weights"`` (the filter's log weights).

    The track's ``infos[t]`` (``t >= 1``) must hold ``hypotheses`` (``K_t x D``) and, per the
    emission, ``mode_energy`` or ``hypothesis_weights`` — what
    :class:`~torchmocap.filters.MixtureInference` records; other inferences raise ``ValueError``.
    """

    def __init__(self, skeleton=None, rotation_std_deg: float = 20.0,
                 translation_std: float = 0.1, emission: str = "energy") -> None:
        super().__init__()
        self.rotation_std_deg, self.translation_std = check_prior_stds(
            rotation_std_deg, translation_std, ("rotation_std_deg", "translation_std"))
        if emission not in EMISSIONS:
            raise ValueError(f"emission: expected one of {EMISSIONS}, got {emission!r}")
        self.emission = emission
        self.translation_dofs = [] if skeleton is None else list(skeleton.translation_dofs)

    def transition_prior(self, num_dofs: int) -> TemporalPrior:
        """The Gaussian of one frame's pose change (``rotation_std_deg``, ``translation_std``)."""
        return TemporalPrior.from_stds(num_dofs, self.translation_dofs, self.rotation_std_deg,
                                       self.translation_std)

    def check(self, inference) -> None:
        if not getattr(inference, "keeps_hypotheses", False):
            raise ValueError(f"smoother: the Viterbi smoother needs an inference that keeps "
                             f"several hypotheses per frame (inference=mixture), got "
                             f"{type(inference).__name__}")

    def candidates(self, track) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Per frame the hypotheses ``(K_t, D)`` and their log emission scores ``(K_t,)``
        (frame 0: the track's first pose, score 0), float64 on the host."""
        theta = track.theta
        D = theta.shape[-1]
        states = [theta[0:1].detach().cpu().to(torch.float64)]  # the infos' modes are on the host
        scores = [torch.zeros(1, dtype=torch.float64)]
        key = "mode_energy" if self.emission == "energy" else "hypothesis_weights"
        for t, info in enumerate(track.infos[1:], start=1):
            if not info.hypotheses or getattr(info, key) is None:
                raise ValueError(f"track.infos[{t}]: no 'hypotheses' and '{key}' - the Viterbi "
                                 "smoother needs an inference that keeps several hypotheses "
                                 "per frame (inference=mixture)")
            H = torch.as_tensor(info.hypotheses, dtype=torch.float64)
            v = torch.as_tensor(getattr(info, key), dtype=torch.float64)
            if H.dim() != 2 or H.shape[1] != D or v.shape != (H.shape[0],):
                raise ValueError(f"track.infos[{t}]: expected hypotheses (K, {D}) and {key} "
                                 f"(K,), got {tuple(H.shape)} and {tuple(v.shape)}")
            e = -v if self.emission == "energy" else torch.log(v.clamp_min(1e-300))
            if not bool(torch.isfinite(H).all()) or not bool(torch.isfinite(e).all()):
                raise ValueError(f"track.infos[{t}]: non-finite hypotheses or {key}")
            states.append(H)
            scores.append(e)
        return states, scores

    def path(self, track) -> tuple[torch.Tensor, list[int], float]:
        """``(theta (T, D), chosen mode per frame, log score)`` of the MAP mode sequence."""
        states, scores = self.candidates(track)
        prior = self.transition_prior(states[0].shape[-1])

        def transition(t):
            return prior.log_prob(states[t][None, :, :], states[t - 1][:, None, :])

        path, score = viterbi_path(scores, transition)
        theta = torch.stack([states[t][k] for t, k in enumerate(path)])
        return theta.to(dtype=track.theta.dtype, device=track.theta.device), path, score

    def smooth(self, track):
        theta, path, _ = self.path(track)
        return dataclasses.replace(track, theta=theta, filtered=track.theta, smoother={
            "name": "viterbi", "modes": path,
            "changed_frames": int((theta != track.theta).any(-1).sum())})

    def extra_repr(self) -> str:
        return (f"rotation_std_deg={self.rotation_std_deg:g}, "
                f"translation_std={self.translation_std:g}, emission={self.emission!r}")
