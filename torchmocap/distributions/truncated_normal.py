"""Normal distribution truncated to an interval: the angular prior of Hauberg & Pedersen (eq. 3).

``p(theta_t | theta_{t-1}) ∝ N(theta_t | theta_{t-1}, diag) U_Theta(theta_t)`` is, per DoF, a
Gaussian around the previous pose restricted to the joint limits ``[low, high]`` *with its
normaliser* (a clamp would pile the mass outside the limits onto them)::

    f(x) = phi((x - loc) / scale) / (scale Z),   Z = Phi(b) - Phi(a),
    a = (low - loc) / scale,  b = (high - loc) / scale,   low <= x <= high

(``phi``/``Phi``: standard normal density and CDF). ``low``/``high`` may be infinite, so a joint
with one limit or none is covered too; use ``.to_event(1)`` for the joint density of a whole pose
(sum over the last dimension).

Numerics. ``log Z`` and every CDF difference are formed as ``log(Phi(u) - Phi(v))`` from
``torch.special.log_ndtr`` on the side of the mean where ``Phi`` is small (by the symmetry
``Phi(u) - Phi(v) = Phi(-v) - Phi(-u)``), with ``log(e^x - e^y) = x + log1mexp(y - x)``, so a
window 8-40 standard deviations out has a finite, accurate normaliser (the naive difference of
two CDFs near 1 is 0). Sampling is exact inverse-CDF sampling in the same orientation: for a
window mostly right of the mean the mirrored window is sampled and mirrored back, and the inverse
of ``log Phi`` is ``ndtri`` refined by Newton steps on ``log_ndtr`` where ``Phi`` underflows;
samples are clamped into the window against rounding. Moments and entropy are evaluated in
float64 (their closed forms cancel in the far tails) and returned in the parameters' dtype.
"""

from __future__ import annotations

import math

import torch
from torch.distributions import Distribution, Independent, constraints

__all__ = ["TruncatedNormal", "log_normal_mass"]

_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)
_LN2 = math.log(2.0)


def _log1mexp(d: torch.Tensor) -> torch.Tensor:
    """``log(1 - exp(d))`` for ``d <= 0`` without cancellation (Maechler's two branches)."""
    return torch.where(d > -_LN2, torch.log(-torch.expm1(d)), torch.log1p(-torch.exp(d)))


def log_normal_mass(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``log(Phi(u) - Phi(v))`` for ``u >= v`` (standard normal CDF ``Phi``), stable everywhere.

    Works on the side of the mean where the CDF is small (``Phi(u) - Phi(v) = Phi(-v) -
    Phi(-u)``), with ``log_ndtr`` and a log-difference of exponentials. ``-inf`` where
    ``u == v``; infinite ``u``/``v`` allowed.

    Args:
        u: ``(*)`` upper standardized limits.
        v: ``(*)`` lower standardized limits (broadcastable with ``u``).
    Returns:
        ``(*)`` log probability mass of ``[v, u]`` under ``N(0, 1)``.

    Example:
        >>> log_normal_mass(torch.tensor(9.0, dtype=torch.float64), torch.tensor(8.0))
        tensor(-35.0136, dtype=torch.float64)
    """
    u, v = torch.broadcast_tensors(u, v)
    flip = (u + v) > 0  # NaN for (inf, -inf): no flip, as wanted
    hi = torch.where(flip, -v, u)
    lo = torch.where(flip, -u, v)
    lh, ll = torch.special.log_ndtr(hi), torch.special.log_ndtr(lo)
    return lh + _log1mexp(torch.clamp(ll - lh, max=0.0))


def _ndtri_log(logp: torch.Tensor, newton_steps: int = 4) -> torch.Tensor:
    """Inverse of ``log Phi``: ``x`` with ``log_ndtr(x) = logp`` (``logp <= 0``).

    ``ndtri(exp(logp))`` where ``exp`` does not underflow; below that (a left tail past ~37
    standard deviations in float64, ~13 in float32) the asymptotic start
    ``-sqrt(-2 logp - log(-4 pi logp))`` refined by Newton steps on ``log_ndtr``.
    """
    tiny = torch.finfo(logp.dtype).tiny
    small = (logp < math.log(tiny) + 10.0) & (logp > -math.inf)  # -inf: ndtri(0) = -inf
    x = torch.special.ndtri(torch.exp(logp))
    if bool(small.any()):
        t = -2.0 * logp.clamp(max=-1.0)
        x0 = -torch.sqrt(t - torch.log(2.0 * math.pi * t))
        for _ in range(newton_steps):
            # d/dx log Phi(x) = phi(x) / Phi(x)
            lphi = -0.5 * x0 * x0 - _LOG_SQRT_2PI
            lnd = torch.special.log_ndtr(x0)
            x0 = x0 - (lnd - logp) * torch.exp(lnd - lphi)
        x = torch.where(small, x0, x)
    return x


def _check_params(loc, scale, low, high) -> None:
    for name, t in (("loc", loc), ("scale", scale), ("low", low), ("high", high)):
        if bool(torch.isnan(t).any()):
            raise ValueError(f"{name}: expected no NaN values")
    if bool(torch.isinf(loc).any()):
        raise ValueError("loc: expected finite values, found inf")
    if not bool(((scale > 0) & torch.isfinite(scale)).all()):
        raise ValueError("scale: expected finite values > 0")
    if not bool((low < high).all()):
        raise ValueError("low, high: expected low < high everywhere (low may be -inf, high +inf)")


class TruncatedNormal(Distribution):
    """Normal distribution ``N(loc, scale^2)`` truncated to ``[low, high]``, batched.

    Args:
        loc: mean of the untruncated normal, e.g. the previous pose ``(D,)`` or ``(P, D)``.
        scale: its standard deviation (``> 0``), e.g. per DoF in radians.
        low, high: the window, ``low < high``; ``-inf``/``+inf`` allowed (unlimited DoF).
            All four broadcast to ``batch_shape``; python numbers are accepted.
        validate_args: the arguments are checked unless ``False`` (``ValueError`` naming the
            argument); with ``True``, ``log_prob`` also rejects values outside the window
            (otherwise their log density is ``-inf``).

    Shapes: ``sample(sample_shape)`` is ``sample_shape + batch_shape``; ``log_prob``, ``cdf`` of
    ``(*)`` broadcast against ``batch_shape``. ``.to_event(1)`` gives the joint density of the
    last dimension (a whole pose).

    Example:
        >>> lo, hi = torch.tensor([0.0, -1.0]), torch.tensor([2.6, float("inf")])
        >>> prior = TruncatedNormal(torch.tensor([0.1, 0.0]), torch.tensor([0.2, 0.3]), lo, hi)
        >>> theta = prior.sample((200,), generator=torch.Generator().manual_seed(0))
        >>> theta.shape, prior.to_event(1).log_prob(theta).shape
        (torch.Size([200, 2]), torch.Size([200]))
    """

    arg_constraints = {
        "loc": constraints.real,
        "scale": constraints.positive,
        "low": constraints.real,  # +-inf allowed (constraints.real only rejects NaN)
        "high": constraints.real,
    }
    has_rsample = False

    def __init__(self, loc, scale, low, high, validate_args: bool | None = None) -> None:
        args = (loc, scale, low, high)
        tensors = [t for t in args if isinstance(t, torch.Tensor)]
        dtype = torch.get_default_dtype()
        floats = [t.dtype for t in tensors if t.is_floating_point()]
        if floats:
            dtype = floats[0]
            for d in floats[1:]:
                dtype = torch.promote_types(dtype, d)
        device = tensors[0].device if tensors else None
        loc, scale, low, high = (torch.as_tensor(t, dtype=dtype, device=device) for t in args)
        if validate_args is not False:
            _check_params(loc, scale, low, high)
        loc, scale, low, high = torch.broadcast_tensors(loc, scale, low, high)
        self.loc, self.scale, self.low, self.high = loc, scale, low, high
        self._a = (low - loc) / scale
        self._b = (high - loc) / scale
        self._log_z = log_normal_mass(self._b, self._a)
        super().__init__(loc.shape, torch.Size(), validate_args=False)
        self._validate_values = bool(validate_args)

    @constraints.dependent_property(is_discrete=False, event_dim=0)
    def support(self):
        return constraints.interval(self.low, self.high)

    def expand(self, batch_shape, _instance=None):
        batch_shape = torch.Size(batch_shape)
        return TruncatedNormal(self.loc.expand(batch_shape), self.scale.expand(batch_shape),
                               self.low.expand(batch_shape), self.high.expand(batch_shape),
                               validate_args=False)

    def to_event(self, reinterpreted_batch_ndims: int = 1) -> Independent:
        """The last ``reinterpreted_batch_ndims`` batch dimensions as one event (pyro's name):
        ``log_prob`` of a whole pose ``(..., D)`` sums over ``D``."""
        return Independent(self, reinterpreted_batch_ndims)

    @property
    def log_normalizer(self) -> torch.Tensor:
        """``log(Phi(b) - Phi(a))``, the log mass of the window under the untruncated normal."""
        return self._log_z

    # -- densities ----------------------------------------------------------------------
    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """Log density ``(*)``; ``-inf`` outside ``[low, high]``."""
        value = torch.as_tensor(value, dtype=self.loc.dtype, device=self.loc.device)
        inside = (value >= self.low) & (value <= self.high)
        if self._validate_values and not bool(inside.all()):
            raise ValueError("value: expected values inside [low, high]")
        z = (value - self.loc) / self.scale
        lp = -0.5 * z * z - _LOG_SQRT_2PI - torch.log(self.scale) - self._log_z
        return torch.where(inside, lp, -math.inf)

    def cdf(self, value: torch.Tensor) -> torch.Tensor:
        """``P(X <= value)`` ``(*)`` (0 below ``low``, 1 above ``high``)."""
        value = torch.as_tensor(value, dtype=self.loc.dtype, device=self.loc.device)
        z = ((value - self.loc) / self.scale).clamp(self._a, self._b)
        return torch.exp(log_normal_mass(z, self._a) - self._log_z).clamp(0.0, 1.0)

    def icdf(self, value: torch.Tensor) -> torch.Tensor:
        """Inverse CDF: the ``x`` in ``[low, high]`` with ``cdf(x) = value`` (``value`` in
        ``[0, 1]``)."""
        value = torch.as_tensor(value, dtype=self.loc.dtype, device=self.loc.device)
        if bool(((value < 0) | (value > 1) | torch.isnan(value)).any()):
            raise ValueError("value: expected probabilities in [0, 1]")
        return self._icdf(value, exact_orientation=True)

    def _icdf(self, u: torch.Tensor, exact_orientation: bool) -> torch.Tensor:
        a, b, log_z = self._a, self._b, self._log_z
        flip = (a + b) > 0  # window mostly right of the mean: invert its mirror image
        lo = torch.where(flip, -b, a)
        hi = torch.where(flip, -a, b)
        if exact_orientation:
            u = torch.where(flip, 1.0 - u, u)
        # Phi(x') = Phi(lo) + u Z, in log space
        log_p = torch.logaddexp(torch.special.log_ndtr(lo), torch.log(u) + log_z)
        xs = _ndtri_log(torch.clamp(log_p, max=0.0))
        xs = torch.minimum(torch.maximum(xs, lo), hi)
        z = torch.where(flip, -xs, xs)
        x = self.loc + self.scale * z
        return torch.minimum(torch.maximum(x, self.low), self.high)

    def sample(self, sample_shape: torch.Size | tuple[int, ...] = (),
               generator: torch.Generator | None = None) -> torch.Tensor:
        """Exact inverse-CDF samples ``sample_shape + batch_shape``, always inside the window.

        Args:
            sample_shape: leading sample dimensions.
            generator: ``torch.Generator`` on the parameters' device (the global RNG if None).
        """
        shape = self._extended_shape(torch.Size(sample_shape))
        with torch.no_grad():
            u = torch.rand(shape, generator=generator, dtype=self.loc.dtype,
                           device=self.loc.device)
            # u in [0, 1): the mirrored orientation samples the same law
            return self._icdf(u, exact_orientation=False)

    # -- moments (closed forms, in float64) ---------------------------------------------
    def _std_terms(self):
        a, b = self._a.double(), self._b.double()
        log_z = log_normal_mass(b, a)

        def phi_over_z(t):  # phi(t) / Z, 0 at infinite t
            return torch.where(torch.isinf(t), 0.0, torch.exp(-0.5 * t * t - _LOG_SQRT_2PI
                                                              - log_z))

        pa, pb = phi_over_z(a), phi_over_z(b)
        ta = torch.where(torch.isinf(a), 0.0, a * pa)  # a phi(a) / Z
        tb = torch.where(torch.isinf(b), 0.0, b * pb)
        return pa, pb, ta, tb, log_z

    @property
    def mean(self) -> torch.Tensor:
        """``loc + scale (phi(a) - phi(b)) / Z``."""
        pa, pb, _, _, _ = self._std_terms()
        return (self.loc.double() + self.scale.double() * (pa - pb)).to(self.loc.dtype)

    @property
    def mode(self) -> torch.Tensor:
        return torch.minimum(torch.maximum(self.loc, self.low), self.high)

    @property
    def variance(self) -> torch.Tensor:
        """``scale^2 [1 + (a phi(a) - b phi(b)) / Z - ((phi(a) - phi(b)) / Z)^2]``."""
        pa, pb, ta, tb, _ = self._std_terms()
        v = 1.0 + (ta - tb) - (pa - pb) ** 2
        return (self.scale.double() ** 2 * v.clamp_min(0.0)).to(self.loc.dtype)

    def entropy(self) -> torch.Tensor:
        """``log(sqrt(2 pi e) scale Z) + (a phi(a) - b phi(b)) / (2 Z)``."""
        _, _, ta, tb, log_z = self._std_terms()
        h = 0.5 + _LOG_SQRT_2PI + torch.log(self.scale.double()) + log_z + 0.5 * (ta - tb)
        return h.to(self.loc.dtype)
