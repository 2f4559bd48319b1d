"""Mixture density propagation (Sminchisescu & Triggs 2003, Fig. 4): a posterior of ``K`` Gaussian
components (mode, inverse-Hessian covariance, weight) carried from frame to frame.

Per frame, :class:`MixtureInference`

1. takes the prior components ``(mu_i, Sigma_i, pi_i)`` of the previous frame from
   ``context.previous_frame.carry`` (first frame: one component at the prediction, its covariance
   the inverse Hessian there), optionally shifted by the predictor's displacement;
2. draws ``num`` samples from the proposal around them — the proposal sees the components as
   ``context.previous (K, D)``, ``context.log_weights`` and ``context.covariances``
   (covariance-scaled sampling, kinematic jumps, or any proposal);
3. optimises every sample locally (and the prior modes themselves), in one batch, within the
   joint limits: damped Gauss–Newton (Levenberg–Marquardt) with the likelihood's analytic
   Gauss–Newton Hessian when every term provides one
   (:meth:`~torchmocap.likelihoods.Joints2DLikelihood.gauss_newton`), projected L-BFGS
   (:func:`~torchmocap.filters.minimise_local`) otherwise;
4. merges minima closer than ``merge_distance`` (largest joint displacement, or Euclidean in
   pose units without a skeleton), keeps the ``K``
   lowest-energy ones, weighs them by ``p(mu_j | r) = exp(-V(mu_j) / temperature)`` and gives
   each the covariance ``Sigma_j = H(mu_j)^-1`` (eigenvalues floored at ``1 / max_std^2``);
5. multiplies each new weight by that of its closest prior component in Bhattacharyya distance
   — matched greedily by increasing distance, a used prior component is discarded (Fig. 4,
   step 5; when all are used the pool is refilled) — and normalises;
6. the estimate is the estimator's choice among the modes (``best_particle``: the top-weighted
   mode); the modes and weights are the returned particle set, the mixture is the ``carry``.

``layers > 1`` repeats steps 2–4 within the frame around the current modes (the minima of every
layer compete). An optional Gaussian temporal prior ``prior_std_deg`` adds
``1/2 sum_d ((x_d - m_d) / sigma_d)^2`` to the optimised energy (``m`` = the prior mode a sample
descends from), which holds the DoFs the observations cannot see (e.g. the twist of a straight
arm); the weights use the likelihood alone.

``info`` per frame: ``hypotheses`` (``K x D`` nested lists of the kept modes),
``hypothesis_weights`` (``K`` floats), ``modes`` (``K``), ``minima`` (distinct minima found),
``samples`` (optimised), ``mode_energy`` (``K`` likelihood energies), ``min_energy``,
``assignment`` (prior component of each mode), ``proposal`` (numeric statistics) and timings.

Example:
    >>> V = lambda x: torch.minimum(((x - 1) ** 2).sum(-1), ((x + 1) ** 2).sum(-1) + 0.1)
    >>> from torchmocap.proposals import CovarianceScaledProposal, ProposalContext
    >>> from torchmocap.filters import BestParticleEstimator
    >>> inf = MixtureInference(components=2, optimiser="lbfgs", hessian="autograd")
    >>> res = inf(V, CovarianceScaledProposal(num_dofs=2, scale=4.0, std_deg=60.0),
    ...           BestParticleEstimator(), ProposalContext(previous=torch.zeros(2)), 50,
    ...           torch.Generator().manual_seed(0))
    >>> res.info["modes"]
    2
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import torch

from torchmocap.distributions.covariance_scaled import hessian_to_covariance
from torchmocap.filters.inference.base import Inference, InferenceResult
from torchmocap.filters.optim.derivatives import DERIVATIVES, HESSIANS, energy_derivatives
from torchmocap.filters.optim.levenberg import levenberg_marquardt
from torchmocap.filters.optim.local import minimise_local
from torchmocap.filters.optim.modes import bhattacharyya_reweight, distinct_minima
from torchmocap.filters.optim.temporal_prior import TemporalPrior
from torchmocap.likelihoods.base import FrameEnergy

__all__ = ["MixtureInference", "gauss_newton_function"]

OPTIMISERS = ("auto", "gauss_newton", "lbfgs", "none")  # "auto" + LOCAL_OPTIMISERS


# ---------------------------------------------------------------------- derivatives
def gauss_newton_function(energy):
    """``fn(theta (P, D), hessian: bool) -> (V (P,), grad (P, D), H (P, D, D) | None)``: the
    analytic Gauss–Newton derivatives of a bound likelihood
    (:class:`~torchmocap.likelihoods.FrameEnergy`) that offers them
    (:meth:`~torchmocap.likelihoods.Likelihood.offers_gauss_newton`); None otherwise (any
    other callable energy)."""
    if isinstance(energy, FrameEnergy) and energy.offers_gauss_newton:
        return energy.gauss_newton
    return None


def _summary(stats: dict) -> dict:
    out = {}
    for k, v in stats.items():
        if isinstance(v, bool):
            continue
        if isinstance(v, (int, float)):
            out[k] = v
        elif isinstance(v, dict) and all(isinstance(x, (int, float)) for x in v.values()):
            out[k] = dict(v)
    return out


# ---------------------------------------------------------------------- the inference module
class MixtureInference(Inference):
    """Mixture density propagation with covariance-scaled proposals and local optimisation
    (module docstring).

    Args:
        skeleton: the tracking model (runtime dependency): joint limits of the optimisation.
        components: ``K``, modes kept per frame.
        layers: sample–optimise rounds per frame (1 = the paper's algorithm).
        iterations: local-optimisation iterations per sample.
        optimiser: ``"auto"`` (Levenberg–Marquardt with Gauss–Newton Hessians when the
            likelihood provides them, else L-BFGS), ``"gauss_newton"``, ``"lbfgs"`` or
            ``"none"`` (no optimisation: the samples are the candidate modes).
        hessian: how mode covariances (and LM Hessians) are computed:
            :func:`energy_derivatives` ``method``.
        merge_distance: minima closer than this are one mode: the largest distance between
            their joints in metres (``merge_space="joints"``, default 0.03) or the Euclidean
            distance of their parameters (``"parameters"``, radians / metres, default 0.05).
        merge_space: ``"joints"`` (needs the skeleton; DoFs that move no joint — the twist of a
            straight limb — do not separate modes), ``"parameters"`` or ``"auto"`` (joints
            with a skeleton).
        temperature: weights ``exp(-V / temperature)``.
        max_std: covariance eigenvalues are floored at ``1 / max_std^2`` (the widest std of a
            mode along a direction the energy does not see).
        prior_std_deg, prior_translation_std: std of the Gaussian temporal prior in the
            optimised energy (None: off).
        prior_in_weights: also weigh each mode by that temporal prior about the prior mode it
            descends from (a kinematic jump then starts with a low weight and takes over only
            when the observations keep preferring it); the paper weighs by the likelihood
            alone (False).
        follow_prediction: shift the prior modes by ``prediction - previous estimate``.
        reoptimise_modes: also optimise the prior modes themselves.
        continuations: keep, before the ``K`` lowest-energy minima are chosen, the best
            *continuation* of each of this many highest-weight prior modes: its
            lowest-energy descendant that was not kinematically jumped (with
            ``reoptimise_modes``, at worst the re-optimised prior mode itself). Jumps then fill
            only the remaining slots, so a tracked interpretation is not pushed out by mirror
            images of equal image cost (0: the paper's plain ``K`` best).
        discard: Fig. 4 step 5's discarding of used prior components.
        lower, upper: box bounds without a skeleton.
    """

    keeps_hypotheses = True
    differentiates_energy = True  # the local optimisation and the modes' covariances

    def __init__(self, skeleton=None, components: int = 8, layers: int = 1,
                 iterations: int = 20, optimiser: str = "auto", hessian: str = "auto",
                 merge_distance: float | None = None, merge_space: str = "auto",
                 temperature: float = 1.0, max_std: float = 0.5,
                 prior_std_deg: float | None = None, prior_translation_std: float = 0.1,
                 prior_in_weights: bool = False, follow_prediction: bool = True,
                 reoptimise_modes: bool = True, discard: bool = True, lower=None,
                 upper=None, continuations: int = 0) -> None:
        super().__init__()
        for name, v, lo in (("components", components, 1), ("layers", layers, 1),
                            ("iterations", iterations, 0), ("continuations", continuations, 0)):
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"{name}: expected an int >= {lo}, got {v!r}")
        if optimiser not in OPTIMISERS:
            raise ValueError(f"optimiser: expected one of {OPTIMISERS}, got {optimiser!r}")
        if hessian not in DERIVATIVES:
            raise ValueError(f"hessian: expected one of {HESSIANS}, got {hessian!r}")
        if merge_distance is None:
            merge_distance = 0.03 if (merge_space == "joints" or (
                merge_space == "auto" and skeleton is not None)) else 0.05
        for name, v in (("merge_distance", merge_distance), ("temperature", temperature),
                        ("max_std", max_std), ("prior_translation_std", prior_translation_std)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v <= 0:
                raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
        if merge_space not in ("auto", "joints", "parameters"):
            raise ValueError(f"merge_space: expected 'auto', 'joints' or 'parameters', got "
                             f"{merge_space!r}")
        if merge_space == "joints" and skeleton is None:
            raise ValueError("merge_space: 'joints' needs the skeleton")
        self.merge_space = ("joints" if skeleton is not None else "parameters") \
            if merge_space == "auto" else merge_space
        self.skeleton = skeleton if self.merge_space == "joints" else None
        if prior_std_deg is not None and not (math.isfinite(prior_std_deg) and prior_std_deg > 0):
            raise ValueError(f"prior_std_deg: expected a finite number > 0 or None, got "
                             f"{prior_std_deg!r}")
        self.components, self.layers, self.iterations = components, layers, iterations
        self.optimiser, self.hessian = optimiser, hessian
        self.merge_distance, self.temperature = float(merge_distance), float(temperature)
        self.max_std = float(max_std)
        self.prior_std_deg = None if prior_std_deg is None else float(prior_std_deg)
        self.prior_translation_std = float(prior_translation_std)
        self.prior_in_weights = bool(prior_in_weights)
        self.follow_prediction = bool(follow_prediction)
        self.reoptimise_modes = bool(reoptimise_modes)
        self.continuations = continuations
        self.discard = bool(discard)
        if skeleton is not None:
            lower = skeleton.lower if lower is None else lower
            upper = skeleton.upper if upper is None else upper
            trans = list(skeleton.translation_dofs)
        else:
            trans = []
        self._translation_dofs = trans
        self.register_buffer("lower", None if lower is None else
                             torch.as_tensor(lower).detach().float().clone())
        self.register_buffer("upper", None if upper is None else
                             torch.as_tensor(upper).detach().float().clone())

    # ------------------------------------------------------------------ pieces
    def _bounds(self, like: torch.Tensor):
        D = like.shape[-1]
        lo = (torch.full((D,), -math.inf, dtype=like.dtype, device=like.device)
              if self.lower is None else self.lower.to(like))
        hi = (torch.full((D,), math.inf, dtype=like.dtype, device=like.device)
              if self.upper is None else self.upper.to(like))
        if lo.shape != (D,) or hi.shape != (D,):
            raise ValueError(f"lower/upper: expected ({D},) bounds, got {tuple(lo.shape)}")
        return lo, hi

    def _merge_coordinates(self, x: torch.Tensor) -> torch.Tensor:
        """What :func:`distinct_minima` compares: joint positions ``(P, J, 3)`` (largest joint
        displacement) or the parameters ``x``."""
        if self.merge_space != "joints":
            return x
        with torch.no_grad():
            return self.skeleton(x.to(self.skeleton.offsets.dtype)).positions

    def _temporal_prior(self, like: torch.Tensor) -> TemporalPrior | None:
        """The Gaussian temporal prior (``prior_std_deg``) in ``like``'s dtype and device."""
        if self.prior_std_deg is None:
            return None
        return TemporalPrior.from_stds(like.shape[-1], self._translation_dofs,
                                       self.prior_std_deg, self.prior_translation_std,
                                       dtype=like.dtype, device=like.device, wrap=False)

    def _derivs_fn(self, energy, anchors: torch.Tensor | None, prior: TemporalPrior | None):
        """``x -> (V_total, grad, H, V_likelihood)`` for rows aligned with ``anchors``."""
        method = self.hessian

        def fn(x, rows=None):
            v, g, H = energy_derivatives(energy, x, True, method,
                                         gauss_newton=gauss_newton_function(energy))
            if g is None:
                raise ValueError("energy: the mixture's local optimisation needs a gradient "
                                 "(a differentiable likelihood)")
            v_lik = v
            if prior is not None and anchors is not None:
                a = anchors if rows is None else anchors[rows]
                v = v + prior.energy(x, a)
                g = g + prior.gradient(x, a)
                H = H + torch.diag_embed(prior.precision.to(x).expand_as(x))
            return v, g, H, v_lik
        return fn

    def _optimise(self, energy, x0, anchors, prior, lo, hi):
        """Locally optimised ``x``, total and likelihood energies, and iterations, by the
        optimiser named in ``self.optimiser`` (:data:`LOCAL_OPTIMISERS`; ``"auto"``:
        Gauss–Newton where the likelihood has it, else L-BFGS)."""
        mode = self.optimiser
        if mode == "auto":
            mode = "gauss_newton" if gauss_newton_function(energy) is not None else "lbfgs"
        if self.iterations == 0:
            mode = "none"
        return LOCAL_OPTIMISERS[mode](self, energy, x0, anchors, prior, lo, hi)

    def _optimise_none(self, energy, x0, anchors, prior, lo, hi):
        with torch.no_grad():
            v_lik = energy(x0)
        v = v_lik if prior is None else v_lik + prior.energy(x0, anchors)
        return x0, v, v_lik, 0

    def _optimise_gauss_newton(self, energy, x0, anchors, prior, lo, hi):
        fn = self._derivs_fn(energy, anchors, prior)

        def derivs(x, rows):
            v, g, H, _ = fn(x, rows)
            return v, g, H

        x, v, _, _, its = levenberg_marquardt(derivs, x0, lo, hi, self.iterations)
        with torch.no_grad():
            v_lik = energy(x)
        return x, v, v_lik.detach(), its

    def _optimise_lbfgs(self, energy, x0, anchors, prior, lo, hi):
        """L-BFGS on V (+ prior) with autograd."""
        if prior is None:
            total = energy
        else:
            def total(x):
                return energy(x) + prior.energy(x, anchors)
        res = minimise_local(total, x0, method="lbfgs", iterations=self.iterations,
                             lower=lo, upper=hi)
        with torch.no_grad():
            v_lik = energy(res.x)
        return res.x.detach(), res.energy.detach(), v_lik.detach(), res.iterations

    def _covariances(self, energy, modes, anchors, prior) -> torch.Tensor:
        fn = self._derivs_fn(energy, anchors, prior)
        _, _, H, _ = fn(modes)
        return hessian_to_covariance(H.double(), floor=1.0 / self.max_std**2).to(modes.dtype)

    def _log_weights(self, v_lik: torch.Tensor, modes=None, origins=None, prior=None
                     ) -> torch.Tensor:
        lw = -v_lik.double() / self.temperature
        if self.prior_in_weights and prior is not None and modes is not None:
            # the temporal prior of each mode about its prior mode
            lw = lw - prior.energy(modes, origins).double()
        lw = torch.where(torch.isfinite(lw), lw, torch.full_like(lw, -1e300))
        return (lw - torch.logsumexp(lw, 0)).to(v_lik.dtype)

    def _selection_order(self, v_lik: torch.Tensor, origin: torch.Tensor, jumped: torch.Tensor,
                         prior_lw: torch.Tensor) -> torch.Tensor:
        """The key :func:`distinct_minima` ranks by: the likelihood energy, with the reserved
        continuations (``continuations``) moved ahead of every other minimum."""
        if not self.continuations:
            return v_lik
        key = v_lik.double().clone()
        finite = torch.isfinite(key)
        if not bool(finite.any()):
            return v_lik
        shift = float(key[finite].max() - key[finite].min()) + 1.0
        top = torch.argsort(prior_lw.double().to(key.device), descending=True)
        for m in top[: self.continuations].tolist():
            cand = ((origin == m) & ~jumped & finite).nonzero().squeeze(1)
            if cand.numel():
                best = cand[key[cand].argmin()]
                key[best] -= shift
        return key

    def _prior(self, energy, context, lo, hi, prior):
        """Prior components ``(means, covs, log_w)`` and whether they came from the carry."""
        prev = context.previous
        D = prev.shape[-1]
        dt = prev.dtype
        carry = None if context.previous_frame is None else context.previous_frame.carry
        if isinstance(carry, dict) and all(k in carry for k in ("means", "covariances",
                                                               "log_weights")):
            means = torch.as_tensor(carry["means"]).to(prev)
            covs = torch.as_tensor(carry["covariances"]).to(prev)
            lw = torch.as_tensor(carry["log_weights"]).to(prev)
            K0 = means.shape[0]
            if means.shape[-1:] == (D,) and covs.shape == (K0, D, D) and lw.shape == (K0,):
                if self.follow_prediction and prev.dim() == 1 and "estimate" in carry:
                    shift = prev - torch.as_tensor(carry["estimate"]).to(prev)
                    means = torch.maximum(torch.minimum(means + shift, hi), lo)
                return means, covs, lw, True
        if prev.dim() == 1:
            means = prev[None]
            lw = torch.zeros(1, dtype=dt, device=prev.device)
        else:
            means = prev
            lw = (torch.full((prev.shape[0],), -math.log(prev.shape[0]), dtype=dt,
                             device=prev.device) if context.log_weights is None
                  else torch.log_softmax(torch.as_tensor(context.log_weights).double(), 0)
                  .to(dt))
        means = torch.maximum(torch.minimum(means, hi), lo)
        covs = self._covariances(energy, means, means, prior)
        return means, covs, lw, False

    # ------------------------------------------------------------------ one frame
    def forward(self, energy, proposal, estimator, context, num: int,
                generator: torch.Generator | None = None) -> InferenceResult:
        t0 = time.perf_counter()
        prev = context.previous
        if not isinstance(prev, torch.Tensor) or prev.dim() not in (1, 2):
            raise ValueError("context.previous: expected a (D,) prediction or (K, D) modes")
        lo, hi = self._bounds(prev)
        prior = self._temporal_prior(prev)
        p_means, p_covs, p_lw, from_carry = self._prior(energy, context, lo, hi, prior)
        K0 = p_means.shape[0]
        modes, covs, lw = p_means, p_covs, p_lw
        mode_origin = torch.arange(K0, device=prev.device)
        X = V = VL = ORIG = ANCH = JMP = None
        stats_all: list[dict] = []
        min_energy: list[float] = []
        samples = 0
        its_total = 0
        t_prop = t_opt = 0.0
        for layer in range(self.layers):
            ctx = dataclasses.replace(context, previous=modes, log_weights=lw, std=None,
                                      scale=1.0, covariances=covs, hessians=None)
            ta = time.perf_counter()
            drawn = proposal.sample(ctx, num, generator)
            t_prop += time.perf_counter() - ta
            stats_all.append(drawn.stats)
            x0 = drawn.particles.to(prev.dtype)
            comp = drawn.stats.get("component") if isinstance(drawn.stats, dict) else None
            if comp is None or torch.as_tensor(comp).shape != (x0.shape[0],):
                # nearest current mode of each sample
                comp = torch.cdist(x0.double(), modes.double()).argmin(-1)
            comp = torch.as_tensor(comp, device=prev.device).long()
            origin = mode_origin[comp]
            # the temporal prior holds a sample near the prior mode it descends from; a
            # kinematic jump is held near its own (jumped) start instead
            jumped = drawn.stats.get("jumped") if isinstance(drawn.stats, dict) else None
            anchors = p_means[origin]
            if jumped is not None and torch.as_tensor(jumped).shape == (x0.shape[0],):
                jumped = torch.as_tensor(jumped, device=prev.device).bool()
                anchors = torch.where(jumped[:, None], x0, anchors)
            else:
                jumped = torch.zeros(x0.shape[0], dtype=torch.bool, device=prev.device)
            if layer == 0 and self.reoptimise_modes:
                x0 = torch.cat([p_means, x0])
                origin = torch.cat([torch.arange(K0, device=prev.device), origin])
                anchors = torch.cat([p_means, anchors])
                jumped = torch.cat([torch.zeros(K0, dtype=torch.bool, device=prev.device),
                                    jumped])
            ta = time.perf_counter()
            x, v, v_lik, its = self._optimise(energy, x0, anchors, prior, lo, hi)
            t_opt += time.perf_counter() - ta
            its_total += its
            samples += x0.shape[0]
            X = x if X is None else torch.cat([X, x])
            V = v if V is None else torch.cat([V, v])
            VL = v_lik if VL is None else torch.cat([VL, v_lik])
            ORIG = origin if ORIG is None else torch.cat([ORIG, origin])
            ANCH = anchors if ANCH is None else torch.cat([ANCH, anchors])
            JMP = jumped if JMP is None else torch.cat([JMP, jumped])
            min_energy.append(float(v_lik.min()))
            reps = distinct_minima(self._merge_coordinates(X),
                                   self._selection_order(VL, ORIG, JMP, p_lw),
                                   self.merge_distance)
            n_minima = int(reps.numel())
            keep = reps[: self.components]
            modes = X[keep]
            mode_origin = ORIG[keep]
            covs = self._covariances(energy, modes, ANCH[keep], prior)
            lw = self._log_weights(VL[keep], modes, p_means[mode_origin], prior)
        v_modes = VL[keep]
        final_lw, assign = bhattacharyya_reweight(modes, covs, lw, p_means, p_covs, p_lw,
                                                  self.discard)
        w = final_lw.exp()
        est = estimator(modes, w, context)
        info: dict[str, Any] = {
            "hypotheses": modes.detach().double().tolist(),
            "hypothesis_weights": [float(a) for a in w.tolist()],
            "modes": int(modes.shape[0]),
            "minima": n_minima,
            "samples": samples,
            "mode_energy": [float(a) for a in v_modes.tolist()],
            "min_energy": min_energy,
            "assignment": [int(a) for a in assign.tolist()],
            "prior_components": K0,
            "from_carry": bool(from_carry),
            "iterations": its_total,
            "proposal": _summary(stats_all[-1]) if stats_all else {},
            "seconds_proposal": t_prop,
            "seconds_optimisation": t_opt,
            "seconds_inference": time.perf_counter() - t0,
        }
        carry = {"means": modes.detach().clone(), "covariances": covs.detach().clone(),
                 "log_weights": final_lw.detach().clone(), "estimate": est.detach().clone()}
        return InferenceResult(estimate=est.detach(), particles=modes.detach(),
                               log_weights=final_lw.detach(), info=info, carry=carry)

    def extra_repr(self) -> str:
        return (f"components={self.components}, layers={self.layers}, iterations="
                f"{self.iterations}, optimiser={self.optimiser!r}, hessian={self.hessian!r}, "
                f"merge_distance={self.merge_distance}, merge_space={self.merge_space!r}, "
                f"prior_std_deg={self.prior_std_deg}, continuations={self.continuations}")


#: the local optimisers of :class:`MixtureInference` by name (``"auto"`` picks one of them)
LOCAL_OPTIMISERS = {
    "none": MixtureInference._optimise_none,
    "gauss_newton": MixtureInference._optimise_gauss_newton,
    "lbfgs": MixtureInference._optimise_lbfgs,
}
