"""The modes of a mixture posterior (Sminchisescu & Triggs 2003, Fig. 4): distinct minima among
optimised samples (:func:`distinct_minima`), and the new components' weights scaled by their
closest prior components in Bhattacharyya distance (:func:`bhattacharyya_reweight`).
"""

from __future__ import annotations

import math

import torch

from torchmocap.distributions.covariance_scaled import bhattacharyya_distance

__all__ = ["bhattacharyya_reweight", "distinct_minima"]


def distinct_minima(x: torch.Tensor, energy: torch.Tensor, tol: float) -> torch.Tensor:
    """Indices of distinct minima, lowest energy first: greedily, the lowest remaining point
    represents every point within ``tol`` of it.

    Args:
        x: ``(P, D)`` optimised points (Euclidean distance) or ``(P, J, 3)`` their joint
            positions (distance = the largest joint displacement).
        energy: ``(P,)``.
        tol: merge distance (pose units, or metres for joint positions).

    Returns:
        ``(M,)`` int64 indices into ``x``.

    Example:
        >>> x = torch.tensor([[0.0], [0.01], [1.0]])
        >>> distinct_minima(x, torch.tensor([1.0, 0.5, 2.0]), 0.05)
        tensor([1, 2])
    """
    if x.dim() not in (2, 3) or energy.shape != x.shape[:1]:
        raise ValueError(f"x: expected (P, D) or (P, J, 3) with energy (P,), got "
                         f"{tuple(x.shape)} and {tuple(energy.shape)}")
    order = torch.argsort(torch.where(torch.isfinite(energy), energy,
                                      torch.full_like(energy, math.inf)))
    xs = x[order].double()
    covered = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    reps = []
    for i in range(x.shape[0]):
        if bool(covered[i]):
            continue
        reps.append(i)
        d = (xs - xs[i]).norm(dim=-1)
        covered |= (d if x.dim() == 2 else d.amax(-1)) <= tol
    return order[torch.tensor(reps, dtype=torch.long, device=x.device)]


def bhattacharyya_reweight(means: torch.Tensor, covs: torch.Tensor, log_weights: torch.Tensor,
                           prior_means: torch.Tensor, prior_covs: torch.Tensor,
                           prior_log_weights: torch.Tensor, discard: bool = True):
    """Fig. 4, steps 5–6: scale each new component's weight by the weight of its closest prior
    component in Bhattacharyya distance and normalise.

    With ``discard`` (the paper's "discard component i") a prior component scales one new
    component only: pairs are matched greedily in order of increasing distance, so a prior mode
    passes its weight to the new mode that continues it (not to whichever new mode has the best
    likelihood); when every prior component is used, the pool is refilled for the remaining new
    components. Without ``discard`` every new component takes its nearest prior component.

    Args:
        means ``(K, D)``, covs ``(K, D, D)``, log_weights ``(K,)``: the new components.
        prior_means ``(K0, D)``, prior_covs ``(K0, D, D)``, prior_log_weights ``(K0,)``.

    Returns:
        normalised log weights ``(K,)`` and the prior index of each component ``(K,)``.

    Example:
        >>> eye = torch.eye(1).expand(2, 1, 1)
        >>> lw, a = bhattacharyya_reweight(torch.tensor([[0.0], [5.0]]), eye,
        ...                                torch.log(torch.tensor([0.5, 0.5])),
        ...                                torch.tensor([[4.9], [0.1]]), eye,
        ...                                torch.log(torch.tensor([0.2, 0.8])))
        >>> lw.exp(), a
        (tensor([0.8000, 0.2000]), tensor([1, 0]))
    """
    K, K0 = means.shape[0], prior_means.shape[0]
    dist = bhattacharyya_distance(means[:, None].double(), covs[:, None].double(),
                                  prior_means[None].double(), prior_covs[None].double()).cpu()
    # the greedy assignment below is a Python loop over K x K0 entries: on the CPU
    assign = torch.full((K,), -1, dtype=torch.long, device=dist.device)
    if not discard:
        assign = dist.argmin(-1)
    else:
        todo = torch.ones(K, dtype=torch.bool, device=dist.device)
        while bool(todo.any()):
            avail = torch.ones(K0, dtype=torch.bool, device=dist.device)
            d = torch.where(todo[:, None] & avail[None], dist, torch.full_like(dist, math.inf))
            for flat in torch.argsort(d.flatten()).tolist():
                j, i = divmod(flat, K0)
                if not bool(todo[j]) or not bool(avail[i]) or not math.isfinite(float(d[j, i])):
                    continue
                assign[j] = i
                todo[j] = False
                avail[i] = False
                if not bool(avail.any()) or not bool(todo.any()):
                    break
    assign = assign.to(means.device)
    lw = log_weights.double() + prior_log_weights.double().to(means.device)[assign]
    return (lw - torch.logsumexp(lw, 0)).to(log_weights.dtype), assign
