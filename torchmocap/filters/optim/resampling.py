"""Resampling for particle filters: multinomial, systematic, stratified and residual.

Every resampler is a pure function ``(log_w (..., N), generator=None, num=None) -> indices
(..., M)`` batched over the leading dims — ``log_w`` unnormalised log weights, ``generator`` the
only source of randomness, ``num`` the number ``M`` of offspring (default ``N``), the result
int64 ancestor indices in ``[0, N)`` — plus a thin class (``MultinomialResampler`` …) for
configs.
Weights are **unnormalised log weights**; they are normalised in log space (``logsumexp``), so
energies of any scale are safe. ``-inf`` means "weight zero" and never receives offspring;
NaN, ``+inf`` and rows without any finite weight are errors.

Traps handled here (see REFERENCE §5):

- A float32 cumulative sum of normalised weights can end at ``1 - 8e-6``: the cumulative sum is
  computed in float64 (where the device supports it), divided by its own last entry so it ends at
  exactly 1, and ``searchsorted`` results are clamped to ``N - 1``.
- A clamp to ``N - 1`` must not hand offspring to a zero-weight last particle: with the
  ``right=True`` search and a CDF ending exactly at 1, a uniform in ``[0, 1)`` always lands on a
  particle of positive weight.
- Residual resampling draws the remainder from ``N·W - floor(N·W)`` (filterpy uses
  ``W - floor(N·W)``, which is biased).
- No resampler gives the last particle an extra offspring (PARSEC bodytrack does, an O(1/N) bias).

Example:
    >>> g = torch.Generator().manual_seed(0)
    >>> systematic_resample(torch.zeros(4, 200), g).shape
    torch.Size([4, 200])
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchmocap.filters.optim.components import as_strategy

__all__ = [
    "Resampler",
    "MultinomialResampler",
    "SystematicResampler",
    "StratifiedResampler",
    "ResidualResampler",
    "check_log_weights",
    "normalize_log_weights",
    "effective_sample_size",
    "ess_fraction",
    "multinomial_resample",
    "systematic_resample",
    "stratified_resample",
    "residual_resample",
    "keep_redraw_resample",
    "KeepRedrawResampler",
    "offspring_counts",
    "counts_to_indices",
    "gather_particles",
    "as_resampler",
]


# --------------------------------------------------------------------------------------------
# validation and weight utilities
# --------------------------------------------------------------------------------------------


def check_log_weights(log_w: torch.Tensor, name: str = "log_w") -> None:
    """Raise a typed error unless ``log_w`` is a valid batch of log weights ``(..., N)``.

    Valid means: a floating tensor with at least one dim, ``N >= 1``, no NaN, no ``+inf``, and at
    least one finite entry per row (``-inf`` entries are zero weights).

    Raises:
        TypeError: ``log_w`` is not a floating-point tensor.
        ValueError: wrong shape, NaN, ``+inf``, or a row whose weights are all zero.
    """
    if not isinstance(log_w, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(log_w).__name__}")
    if not log_w.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {log_w.dtype}")
    if log_w.dim() < 1 or log_w.shape[-1] < 1:
        raise ValueError(f"{name}: expected shape (..., N) with N >= 1, got {tuple(log_w.shape)}")
    if bool(torch.isfinite(log_w).all()):  # the common case: one test
        return
    if bool(torch.isnan(log_w).any()):
        raise ValueError(f"{name}: contains NaN log weights")
    if bool((log_w == float("inf")).any()):
        raise ValueError(f"{name}: contains +inf log weights")
    if bool((~torch.isfinite(log_w)).all(dim=-1).any()):
        raise ValueError(f"{name}: a row has no particle of positive weight (all -inf)")


def normalize_log_weights(log_w: torch.Tensor) -> torch.Tensor:
    """Normalised log weights ``log W = log_w - logsumexp(log_w)``, ``(..., N) -> (..., N)``."""
    check_log_weights(log_w)
    return log_w - torch.logsumexp(log_w, dim=-1, keepdim=True)


def effective_sample_size(log_w: torch.Tensor) -> torch.Tensor:
    """Effective sample size ``1 / Σ W²`` of (unnormalised) log weights ``(..., N) -> (...)``.

    Computed as ``exp(2·lse(log_w) − lse(2·log_w))``, so it never exponentiates raw weights.
    Lies in ``[1, N]``. (Hauberg & Pedersen's eq. 17 prints ``(Σw)⁻¹`` — a typo.)
    """
    check_log_weights(log_w)
    return torch.exp(2.0 * torch.logsumexp(log_w, dim=-1) - torch.logsumexp(2.0 * log_w, dim=-1))


def ess_fraction(log_w: torch.Tensor) -> torch.Tensor:
    """Effective sample size divided by ``N``: ``(..., N) -> (...)``, in ``[1/N, 1]``."""
    return effective_sample_size(log_w) / log_w.shape[-1]


# --------------------------------------------------------------------------------------------
# internals
# --------------------------------------------------------------------------------------------


def _work_dtype(x: torch.Tensor) -> torch.dtype:
    """float64 for cumulative sums unless the device lacks it (MPS)."""
    return x.dtype if x.device.type == "mps" else torch.float64


def _cdf(log_w: torch.Tensor) -> torch.Tensor:
    """Cumulative distribution ``(..., N)`` ending at exactly 1 (float64 where possible)."""
    w = torch.exp(normalize_log_weights(log_w.to(_work_dtype(log_w))))
    c = torch.cumsum(w, dim=-1)
    return c / c[..., -1:]


def _search(cdf: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Indices ``i`` with ``cdf[i-1] <= u < cdf[i]`` for uniforms ``u (..., M)`` in ``[0, 1)``."""
    lead = cdf.shape[:-1]
    n = cdf.shape[-1]
    c2 = cdf.reshape(-1, n).contiguous()
    u2 = u.to(cdf.dtype).reshape(c2.shape[0], -1).contiguous()
    idx = torch.searchsorted(c2, u2, right=True)
    return idx.clamp_(max=n - 1).reshape(*lead, -1)


def _uniform(shape: tuple[int, ...], like: torch.Tensor, generator: torch.Generator | None):
    return torch.rand(shape, generator=generator, dtype=_work_dtype(like), device=like.device)


def _num(log_w: torch.Tensor, num: int | None) -> int:
    if num is None:
        return log_w.shape[-1]
    if not isinstance(num, int) or num < 0:
        raise ValueError(f"num: expected a non-negative int, got {num!r}")
    return num


# --------------------------------------------------------------------------------------------
# resamplers
# --------------------------------------------------------------------------------------------


def multinomial_resample(
    log_w: torch.Tensor, generator: torch.Generator | None = None, num: int | None = None
) -> torch.Tensor:
    """Multinomial resampling: ``M`` i.i.d. draws from the categorical ``W`` (indices
    unsorted; arguments in the module docstring)."""
    check_log_weights(log_w)
    m = _num(log_w, num)
    cdf = _cdf(log_w)
    u = _uniform((*log_w.shape[:-1], m), log_w, generator)
    return _search(cdf, u)


def _strata_resample(log_w, generator, num, shared_offset: bool) -> torch.Tensor:
    """``u_j = (j + U) / M`` with one ``U`` per row (systematic) or one per stratum (stratified)."""
    check_log_weights(log_w)
    m = _num(log_w, num)
    cdf = _cdf(log_w)
    base = torch.arange(m, dtype=cdf.dtype, device=cdf.device)
    k = 1 if shared_offset else m
    u = (base + _uniform((*log_w.shape[:-1], k), log_w, generator)) / m
    return _search(cdf, u.clamp_(max=1.0 - torch.finfo(cdf.dtype).eps))


def systematic_resample(
    log_w: torch.Tensor, generator: torch.Generator | None = None, num: int | None = None
) -> torch.Tensor:
    """Systematic resampling: one uniform per row, ``u_j = (j + U) / M``; each particle gets
    ``floor(M·W_i)`` or ``ceil(M·W_i)`` offspring, unbiased (indices sorted ascending)."""
    return _strata_resample(log_w, generator, num, shared_offset=True)


def stratified_resample(
    log_w: torch.Tensor, generator: torch.Generator | None = None, num: int | None = None
) -> torch.Tensor:
    """Stratified resampling: one uniform per stratum, ``u_j = (j + U_j) / M`` (indices sorted
    ascending)."""
    return _strata_resample(log_w, generator, num, shared_offset=False)


def residual_resample(
    log_w: torch.Tensor, generator: torch.Generator | None = None, num: int | None = None
) -> torch.Tensor:
    """Residual resampling: ``floor(M·W_i)`` deterministic copies, the rest multinomial.

    The ``R = M − Σ floor(M·W_i)`` remaining offspring are drawn from the residual weights
    ``M·W_i − floor(M·W_i)`` (normalised by ``R``) — not filterpy's biased ``W_i − floor(M·W_i)``
    (indices sorted ascending)."""
    check_log_weights(log_w)
    m = _num(log_w, num)
    n = log_w.shape[-1]
    lead = log_w.shape[:-1]
    w = torch.exp(normalize_log_weights(log_w.to(_work_dtype(log_w))))
    w = w / w.sum(dim=-1, keepdim=True)
    mw = m * w
    copies = torch.floor(mw)
    residual = (mw - copies).clamp_(min=0.0)
    copies = copies.to(torch.int64)
    r = m - copies.sum(dim=-1)  # (...,) number of residual draws per row
    counts = copies.reshape(-1, n)
    if m > 0:
        res2 = residual.reshape(-1, n)
        tot = res2.sum(dim=-1, keepdim=True)
        has = tot[:, 0] > 0
        # rows without residual mass (r == 0) get a dummy uniform CDF; their draws are masked out
        res2 = torch.where(has[:, None], res2, torch.ones_like(res2))
        c = torch.cumsum(res2, dim=-1)
        c = c / c[:, -1:]
        u = _uniform((res2.shape[0], m), log_w, generator)
        draws = _search(c, u)
        keep = torch.arange(m, device=log_w.device)[None, :] < r.reshape(-1, 1)
        counts = counts.scatter_add(-1, draws, keep.to(torch.int64))
    return counts_to_indices(counts.reshape(*lead, n))


def keep_redraw_resample(
    log_w: torch.Tensor, generator: torch.Generator | None = None, num: int | None = None
) -> torch.Tensor:
    """Gall's interacting-simulated-annealing selection: keep or redraw each particle.

    Particle ``i`` keeps its own slot with probability ``W_i / max W``; every other slot is
    redrawn from the whole weighted set (multinomial). Unbiased:
    ``E[count_i] = W_i/W_max + N·W_i − W_i/W_max = N·W_i``. With nearly uniform weights most
    particles survive unchanged (less sample impoverishment than multinomial).

    Args:
        log_w: ``(..., N)`` unnormalised log weights.
        generator: source of randomness.
        num: must be ``None`` or ``N`` (slots are the particles themselves).
    Returns:
        ``(..., N)`` int64 ancestor indices; slot ``i`` holds ``i`` when kept.
    """
    check_log_weights(log_w)
    n = log_w.shape[-1]
    if num is not None and num != n:
        raise ValueError(f"num: keep/redraw selection returns N = {n} indices, got num={num}")
    lw = log_w.to(_work_dtype(log_w))
    keep_prob = torch.exp(lw - lw.amax(dim=-1, keepdim=True))
    keep = _uniform(tuple(log_w.shape), log_w, generator) < keep_prob
    redraw = multinomial_resample(log_w, generator)
    own = torch.arange(n, device=log_w.device).expand_as(redraw)
    return torch.where(keep, own, redraw)


def offspring_counts(indices: torch.Tensor, num_particles: int) -> torch.Tensor:
    """Number of offspring of each particle: int64 ``indices (..., M) -> counts (..., N)``."""
    if not isinstance(indices, torch.Tensor) or indices.dtype not in (torch.int64, torch.int32):
        raise TypeError("indices: expected an integer torch.Tensor")
    if indices.dim() < 1:
        raise ValueError(f"indices: expected shape (..., M), got {tuple(indices.shape)}")
    counts = torch.zeros(
        (*indices.shape[:-1], num_particles), dtype=torch.int64, device=indices.device
    )
    return counts.scatter_add_(-1, indices.long(), torch.ones_like(indices, dtype=torch.int64))


def counts_to_indices(counts: torch.Tensor) -> torch.Tensor:
    """Sorted ancestor indices from offspring counts: ``(..., N) -> (..., M)``, ``M = Σ counts``.

    Every row must have the same total ``M``.
    """
    if counts.dim() < 1:
        raise ValueError(f"counts: expected shape (..., N), got {tuple(counts.shape)}")
    n = counts.shape[-1]
    cum = torch.cumsum(counts, dim=-1)
    totals = cum[..., -1]
    m = int(totals.reshape(-1)[0]) if totals.numel() else 0
    if bool((totals != m).any()):
        raise ValueError("counts: every row must have the same total number of offspring")
    lead = counts.shape[:-1]
    c2 = cum.reshape(-1, n).contiguous()
    j = torch.arange(m, device=counts.device, dtype=cum.dtype).expand(c2.shape[0], m).contiguous()
    return torch.searchsorted(c2, j, right=True).clamp_(max=n - 1).reshape(*lead, m)


def gather_particles(particles: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
    """Select particles by ancestor index: ``particles (..., N, D)``, ``indices (..., M)`` →
    ``(..., M, D)``."""
    if particles.dim() < 2 or particles.shape[:-2] != indices.shape[:-1]:
        raise ValueError(
            f"particles: expected shape (..., N, D) matching indices (..., M); got "
            f"{tuple(particles.shape)} and {tuple(indices.shape)}"
        )
    idx = indices[..., None].expand(*indices.shape, particles.shape[-1])
    return torch.gather(particles, -2, idx)


# --------------------------------------------------------------------------------------------
# thin classes
# --------------------------------------------------------------------------------------------


class Resampler:
    """Base class: ``resampler(log_w (..., N), generator) -> indices (..., N)``."""

    fn: Callable[..., torch.Tensor]

    def __call__(
        self,
        log_w: torch.Tensor,
        generator: torch.Generator | None = None,
        num: int | None = None,
    ) -> torch.Tensor:
        return type(self).fn(log_w, generator, num)

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class MultinomialResampler(Resampler):
    """Thin wrapper of :func:`multinomial_resample`."""

    fn = staticmethod(multinomial_resample)


class SystematicResampler(Resampler):
    """Thin wrapper of :func:`systematic_resample`."""

    fn = staticmethod(systematic_resample)


class StratifiedResampler(Resampler):
    """Thin wrapper of :func:`stratified_resample`."""

    fn = staticmethod(stratified_resample)


class ResidualResampler(Resampler):
    """Thin wrapper of :func:`residual_resample`."""

    fn = staticmethod(residual_resample)


class KeepRedrawResampler(Resampler):
    """Thin wrapper of :func:`keep_redraw_resample` (Gall's ISA selection)."""

    fn = staticmethod(keep_redraw_resample)


def as_resampler(resampler: Resampler | Callable[..., torch.Tensor] | None,
                 arg: str = "resampler", default: type[Resampler] = SystematicResampler
                 ) -> Callable[..., torch.Tensor]:
    """``resampler`` itself (a callable ``(log_w, generator) -> indices``), or ``default()`` for
    ``None``. Resamplers are objects: a config chooses one by its ``_target_``."""
    return as_strategy(resampler, arg, default, "resampler object such as "
                       "torchmocap.filters.SystematicResampler()")
