"""Covariance-scaled sampling (Sminchisescu & Triggs 2001/2003, §4) and its Gaussian toolkit.

Covariance-scaled sampling (CSS) draws around a local optimum ``mu`` of a cost from
``N(mu, s Sigma)`` — ``Sigma`` the inverse Hessian of the cost at ``mu``, ``s ~ 4-16`` — or from a
heavy-tailed version with the same scale matrix (multivariate Student-t, Cauchy), so samples
probe deep along the cost's shallow directions. Spherical sampling (SS) is the same with the
isotropic covariance of equal volume, ``R I`` with ``R = (lambda_1 ... lambda_n)^(1/n)``.

* :func:`covariance_scaled_sample` — CSS/SS samples, one or ``K`` components;
* :func:`mixture_covariance_scaled_sample` — from the mixture ``sum_k pi_k N(mu_k, s Sigma_k)``
  (the proposal of their Fig. 4, step 1);
* :func:`spherical_covariance` — the equal-volume isotropic covariance (log space);
* :func:`bhattacharyya_distance` — between Gaussians (Fig. 4, step 5), via Cholesky;
* :func:`hessian_to_covariance` — ``Sigma = H^-1`` for a possibly indefinite Hessian.

Heavy tails: ``x = mu + sqrt(s) L z / sqrt(g / nu)`` with ``z ~ N(0, I)``, ``g ~ chi^2_nu`` shared
by the components of one sample (the elliptical multivariate t; ``nu = 1`` is the Cauchy), so
each whitened coordinate ``(L^-1 (x - mu))_i / sqrt(s)`` is Student-t with ``nu`` degrees of
freedom. ``s Sigma`` is the *scale* matrix: the covariance is ``s Sigma nu / (nu - 2)`` for
``nu > 2`` and infinite otherwise. All randomness comes from the ``torch.Generator`` passed in
(the chi-square draws use a Marsaglia–Tsang gamma sampler built on it).

Example:
    >>> g = torch.Generator().manual_seed(0)
    >>> covariance_scaled_sample(torch.zeros(3), torch.eye(3), 5, scale=4.0, generator=g).shape
    torch.Size([5, 3])
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = [
    "CovarianceScaledSampler",
    "bhattacharyya_distance",
    "covariance_scaled_sample",
    "hessian_to_covariance",
    "mixture_covariance_scaled_sample",
    "spherical_covariance",
]

_TAILS = ("gaussian", "student_t", "cauchy")


# ---------------------------------------------------------------------- checks
def _check_tensor(x, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name}: expected finite values, found NaN or inf")
    return x


def _check_square(x: torch.Tensor, name: str, lead: str = "*") -> None:
    if x.dim() < 2 or x.shape[-1] != x.shape[-2]:
        raise ValueError(f"{name}: expected shape ({lead}, D, D), got {tuple(x.shape)}")


def _symmetric(x: torch.Tensor, name: str) -> torch.Tensor:
    tol = (1e-10 if x.dtype == torch.float64 else 1e-5) * x.abs().amax().clamp_min(1.0)
    if float((x - x.transpose(-1, -2)).abs().amax()) > float(tol):
        raise ValueError(f"{name}: expected symmetric matrices")
    return 0.5 * (x + x.transpose(-1, -2))


def _cholesky(cov: torch.Tensor, name: str) -> torch.Tensor:
    """Lower Cholesky factor of a symmetric positive-definite ``(*, D, D)``; a clear error
    otherwise."""
    L, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        raise ValueError(f"{name}: expected symmetric positive-definite matrices (Cholesky "
                         "failed); regularise it or use hessian_to_covariance")
    return L


def _sqrt_factor(cov: torch.Tensor, name: str) -> torch.Tensor:
    """A factor ``A`` with ``A A^T = cov`` for positive *semi*-definite ``cov``: Cholesky when it
    succeeds, the symmetric square root from ``eigh`` (eigenvalues clamped at 0) otherwise."""
    L, info = torch.linalg.cholesky_ex(cov)
    if not bool((info != 0).any()):
        return L
    lam, V = torch.linalg.eigh(cov)
    tol = 1e3 * torch.finfo(cov.dtype).eps * lam.abs().amax(-1, keepdim=True)
    if bool((lam < -tol).any()):
        raise ValueError(f"{name}: expected positive semi-definite matrices, found an "
                         f"eigenvalue of {float(lam.min()):.3g}")
    return V * lam.clamp_min(0).sqrt()[..., None, :]


# ---------------------------------------------------------------------- random variates
def _standard_gamma(shape: torch.Tensor | float, size: tuple[int, ...],
                    generator: torch.Generator | None, dtype: torch.dtype,
                    device: torch.device) -> torch.Tensor:
    """Gamma(shape, 1) variates by Marsaglia & Tsang (2000), vectorised with a capped number of
    rounds; ``shape < 1`` uses ``Gamma(a) = Gamma(a + 1) U^(1/a)``."""
    a = torch.as_tensor(shape, dtype=dtype, device=device).expand(size)
    boost = a < 1
    a1 = torch.where(boost, a + 1, a)
    d = a1 - 1.0 / 3.0
    c = 1.0 / torch.sqrt(9 * d)
    tiny = torch.finfo(dtype).tiny
    out = torch.empty(size, dtype=dtype, device=device)
    todo = torch.ones(size, dtype=torch.bool, device=device)
    for _ in range(64):  # acceptance >= 95% per round
        x = torch.randn(size, generator=generator, dtype=dtype, device=device)
        u = torch.rand(size, generator=generator, dtype=dtype, device=device)
        v = (1 + c * x) ** 3
        ok = (v > 0) & (torch.log(u.clamp_min(tiny))
                        < 0.5 * x * x + d - d * v + d * torch.log(v.clamp_min(tiny)))
        take = ok & todo
        out = torch.where(take, d * v, out)
        todo = todo & ~take
        if not bool(todo.any()):
            break
    else:  # pragma: no cover - probability < 1e-80
        raise RuntimeError("gamma sampler did not converge")
    u = torch.rand(size, generator=generator, dtype=dtype, device=device)
    scale = torch.where(boost, u.clamp_min(tiny) ** (1.0 / a), torch.ones_like(u))
    return out * scale


def _tail_scale(tails: str, dof: float | None, n: tuple[int, ...], generator,
                dtype: torch.dtype, device: torch.device) -> torch.Tensor | None:
    """Per-sample factor ``1 / sqrt(g / nu)``, ``g ~ chi^2_nu`` (``None`` for Gaussian tails)."""
    if tails == "gaussian":
        return None
    nu = 1.0 if tails == "cauchy" else float(dof)
    chi2 = 2 * _standard_gamma(nu / 2, n, generator, dtype, device)
    return torch.rsqrt(chi2.clamp_min(torch.finfo(dtype).tiny) / nu)


def _check_tails(tails: str, dof: float | None) -> None:
    if tails not in _TAILS:
        raise ValueError(f"tails: expected one of {_TAILS}, got {tails!r}")
    if tails == "student_t":
        if dof is None or not (math.isfinite(float(dof)) and float(dof) > 0):
            raise ValueError(f"dof: expected a finite number > 0 for Student-t tails, got {dof}")


# ---------------------------------------------------------------------- sampling
def covariance_scaled_sample(
    mean: torch.Tensor,
    cov: torch.Tensor,
    num: int,
    scale: float = 4.0,
    tails: str = "gaussian",
    dof: float | None = None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Covariance-scaled samples around one or ``K`` modes.

    Args:
        mean: ``(D,)`` or ``(K, D)`` modes.
        cov: ``(D, D)`` or ``(K, D, D)`` symmetric positive semi-definite covariances (e.g.
            :func:`hessian_to_covariance` of the cost's Hessian; :func:`spherical_covariance`
            of it for spherical sampling).
        num: samples per component, ``>= 0``.
        scale: ``s > 0``; the scale matrix is ``s * cov`` (standard deviations grow by
            ``sqrt(s)``).
        tails: ``"gaussian"``, ``"student_t"`` (needs ``dof``) or ``"cauchy"``.
        dof: degrees of freedom ``nu > 0`` of the Student-t.
        generator: the source of randomness (the global RNG is used only when ``None``).

    Returns:
        ``(num, D)`` for a single mode, ``(num, K, D)`` for ``K`` modes (sample shape first).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> x = covariance_scaled_sample(torch.zeros(2, 4), torch.eye(4).expand(2, 4, 4), 100,
        ...                              scale=8.0, tails="cauchy", generator=g)
        >>> x.shape
        torch.Size([100, 2, 4])
    """
    mean = _check_tensor(mean, "mean")
    cov = _check_tensor(cov, "cov")
    if mean.dim() not in (1, 2):
        raise ValueError(f"mean: expected shape (D,) or (K, D), got {tuple(mean.shape)}")
    D = mean.shape[-1]
    if cov.shape[-2:] != (D, D) or cov.dim() not in (2, 3):
        raise ValueError(f"cov: expected shape ({D}, {D}) or (K, {D}, {D}), got "
                         f"{tuple(cov.shape)}")
    if cov.dim() == 3 and mean.dim() == 2 and cov.shape[0] != mean.shape[0]:
        raise ValueError(f"cov: expected {mean.shape[0]} covariances to match mean, got "
                         f"{cov.shape[0]}")
    if not isinstance(num, int) or num < 0:
        raise ValueError(f"num: expected an integer >= 0, got {num!r}")
    if not (math.isfinite(float(scale)) and float(scale) > 0):
        raise ValueError(f"scale: expected a finite number > 0, got {scale}")
    _check_tails(tails, dof)
    single = mean.dim() == 1 and cov.dim() == 2
    cov = _symmetric(cov.to(mean.dtype), "cov")
    A = _sqrt_factor(cov, "cov")
    batch = torch.broadcast_shapes(mean.shape[:-1], cov.shape[:-2])
    dt, dev = mean.dtype, mean.device
    z = torch.randn(num, *batch, D, generator=generator, dtype=dt, device=dev)
    y = (A @ z[..., None])[..., 0] * math.sqrt(float(scale))
    w = _tail_scale(tails, dof, (num, *batch), generator, dt, dev)
    if w is not None:
        y = y * w[..., None]
    x = mean + y
    return x.reshape(num, D) if single else x


def mixture_covariance_scaled_sample(
    weights: torch.Tensor, means: torch.Tensor, covs: torch.Tensor, num: int,
    scale: float = 4.0, tails: str = "gaussian", dof: float | None = None,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples from ``sum_k pi_k N(mu_k, s Sigma_k)`` (or its heavy-tailed version).

    Args:
        weights: ``(K,)`` non-negative mixture weights (normalised here; not all zero).
        means: ``(K, D)``; covs: ``(K, D, D)``; other arguments as
            :func:`covariance_scaled_sample`.

    Returns:
        ``samples (num, D)`` and ``components (num,)`` (int64 index of each sample's mode).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> x, k = mixture_covariance_scaled_sample(torch.tensor([0.3, 0.7]), torch.zeros(2, 3),
        ...                                         torch.eye(3).expand(2, 3, 3), 10, generator=g)
        >>> x.shape, k.shape
        (torch.Size([10, 3]), torch.Size([10]))
    """
    weights = _check_tensor(weights, "weights")
    means = _check_tensor(means, "means")
    covs = _check_tensor(covs, "covs")
    if means.dim() != 2:
        raise ValueError(f"means: expected shape (K, D), got {tuple(means.shape)}")
    K, D = means.shape
    if weights.shape != (K,):
        raise ValueError(f"weights: expected shape ({K},), got {tuple(weights.shape)}")
    if covs.shape != (K, D, D):
        raise ValueError(f"covs: expected shape ({K}, {D}, {D}), got {tuple(covs.shape)}")
    if bool((weights < 0).any()) or not float(weights.sum()) > 0:
        raise ValueError("weights: expected non-negative values with a positive sum")
    if not isinstance(num, int) or num < 0:
        raise ValueError(f"num: expected an integer >= 0, got {num!r}")
    if not (math.isfinite(float(scale)) and float(scale) > 0):
        raise ValueError(f"scale: expected a finite number > 0, got {scale}")
    _check_tails(tails, dof)
    k = torch.multinomial(weights.to(device=means.device, dtype=torch.float64), num,
                          replacement=True, generator=generator)
    A = _sqrt_factor(_symmetric(covs.to(means.dtype), "covs"), "covs")
    dt, dev = means.dtype, means.device
    z = torch.randn(num, D, generator=generator, dtype=dt, device=dev)
    y = (A[k] @ z[..., None])[..., 0] * math.sqrt(float(scale))
    w = _tail_scale(tails, dof, (num,), generator, dt, dev)
    if w is not None:
        y = y * w[..., None]
    return means[k] + y, k


# ---------------------------------------------------------------------- covariances
def spherical_covariance(cov: torch.Tensor) -> torch.Tensor:
    """Isotropic covariance ``R I`` with the volume (determinant) of ``cov``.

    ``R = (lambda_1 ... lambda_n)^(1/n) = exp(log det(cov) / n)``, the log-determinant from the
    Cholesky factor, so tiny or huge eigenvalues do not under/overflow the product (30
    eigenvalues of ``1e-12`` give ``R = 1e-12``, where the plain product underflows to 0).

    Args:
        cov: ``(*, D, D)`` symmetric positive-definite.

    Returns:
        ``(*, D, D)``.

    Example:
        >>> spherical_covariance(torch.diag(torch.tensor([4.0, 1.0])))
        tensor([[2., 0.],
                [0., 2.]])
    """
    cov = _check_tensor(cov, "cov")
    _check_square(cov, "cov")
    cov = _symmetric(cov, "cov")
    L = _cholesky(cov, "cov")
    D = cov.shape[-1]
    logdet = 2 * torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)
    R = torch.exp(logdet / D)
    eye = torch.eye(D, dtype=cov.dtype, device=cov.device)
    return R[..., None, None] * eye


def hessian_to_covariance(
    hessian: torch.Tensor,
    floor: float = 0.0,
    rel_floor: float = 1e-8,
    mode: str = "abs",
) -> torch.Tensor:
    """``Sigma = H^-1`` of a cost's Hessian, safe for indefinite or singular ``H``.

    ``H`` is symmetrised and diagonalised, ``H = V diag(lambda) V^T``; each eigenvalue becomes
    ``max(|lambda|, f)`` (``mode="abs"``: saddle directions are treated like their curvature
    magnitude, as in saddle-free Newton) or ``max(lambda, f)`` (``mode="clamp"``: negative or
    flat directions get the widest allowed spread ``1/f``), with the floor
    ``f = max(floor, rel_floor * max|lambda|, tiny)``; ``Sigma = V diag(1/lambda') V^T`` is
    symmetric positive definite with condition number at most ``1 / rel_floor``.

    Args:
        hessian: ``(*, D, D)``.
        floor: absolute eigenvalue floor (cost units per squared parameter unit).
        rel_floor: floor relative to the largest eigenvalue magnitude, in ``(0, 1]``.
        mode: ``"abs"`` or ``"clamp"``.

    Returns:
        ``(*, D, D)`` covariances.

    Example:
        >>> hessian_to_covariance(torch.diag(torch.tensor([4.0, -2.0])))
        tensor([[0.2500, 0.0000],
                [0.0000, 0.5000]])
    """
    H = _check_tensor(hessian, "hessian")
    _check_square(H, "hessian")
    if mode not in ("abs", "clamp"):
        raise ValueError(f"mode: expected 'abs' or 'clamp', got {mode!r}")
    if not (math.isfinite(floor) and floor >= 0):
        raise ValueError(f"floor: expected a finite number >= 0, got {floor}")
    if not 0 < rel_floor <= 1:
        raise ValueError(f"rel_floor: expected a number in (0, 1], got {rel_floor}")
    H = 0.5 * (H + H.transpose(-1, -2))
    lam, V = torch.linalg.eigh(H)
    big = lam.abs().amax(-1, keepdim=True)
    f = torch.clamp(torch.maximum(rel_floor * big, torch.full_like(big, float(floor))),
                    min=torch.finfo(H.dtype).tiny ** 0.5)
    lam2 = lam.abs() if mode == "abs" else lam
    lam2 = torch.maximum(lam2, f)
    cov = (V / lam2[..., None, :]) @ V.transpose(-1, -2)
    return 0.5 * (cov + cov.transpose(-1, -2))


def bhattacharyya_distance(
    mean1: torch.Tensor, cov1: torch.Tensor, mean2: torch.Tensor, cov2: torch.Tensor
) -> torch.Tensor:
    """Bhattacharyya distance ``-log int sqrt(p q)`` between two Gaussians.

    ``D_B = 1/8 dm^T S^-1 dm + 1/2 log(det S / sqrt(det S1 det S2))``, ``S = (S1 + S2) / 2``;
    solves and log-determinants through Cholesky factors (no explicit inverse, no determinant
    products that under/overflow). Zero for identical Gaussians, symmetric, batched.

    Args:
        mean1, mean2: ``(*, D)``.
        cov1, cov2: ``(*, D, D)`` symmetric positive-definite (all four broadcast).

    Returns:
        ``(*)`` distances (nats), ``>= 0``.

    Example:
        >>> bhattacharyya_distance(torch.zeros(1), torch.eye(1), torch.ones(1), torch.eye(1))
        tensor(0.1250)
    """
    for x, n in ((mean1, "mean1"), (cov1, "cov1"), (mean2, "mean2"), (cov2, "cov2")):
        _check_tensor(x, n)
    if mean1.dim() < 1 or mean2.dim() < 1:
        raise ValueError(f"mean1/mean2: expected shape (*, D), got {tuple(mean1.shape)} and "
                         f"{tuple(mean2.shape)}")
    D = mean1.shape[-1]
    if mean2.shape[-1] != D:
        raise ValueError(f"mean2: expected last dim {D} like mean1, got {tuple(mean2.shape)}")
    for c, n in ((cov1, "cov1"), (cov2, "cov2")):
        if c.dim() < 2 or c.shape[-2:] != (D, D):
            raise ValueError(f"{n}: expected shape (*, {D}, {D}), got {tuple(c.shape)}")
    cov1, cov2 = _symmetric(cov1, "cov1"), _symmetric(cov2, "cov2")
    L1, L2 = _cholesky(cov1, "cov1"), _cholesky(cov2, "cov2")
    S = 0.5 * (cov1 + cov2)
    L = _cholesky(S, "cov1 + cov2")
    dm = mean1 - mean2
    batch = torch.broadcast_shapes(dm.shape[:-1], L.shape[:-2])
    y = torch.linalg.solve_triangular(L.expand(*batch, D, D), dm.expand(*batch, D)[..., None],
                                      upper=False)[..., 0]

    def logdet(F: torch.Tensor) -> torch.Tensor:
        return 2 * torch.log(F.diagonal(dim1=-2, dim2=-1)).sum(-1)

    out = 0.125 * (y * y).sum(-1) + 0.5 * (logdet(L) - 0.5 * (logdet(L1) + logdet(L2)))
    return out.clamp_min(0)


class CovarianceScaledSampler(nn.Module):
    """Thin module around :func:`covariance_scaled_sample` holding ``scale``, ``tails``, ``dof``
    and whether to sample spherically (SS: :func:`spherical_covariance` of each ``cov``).

    Example:
        >>> css = CovarianceScaledSampler(scale=8.0, tails="student_t", dof=3.0)
        >>> css(torch.zeros(4), torch.eye(4), 10, generator=torch.Generator().manual_seed(0)).shape
        torch.Size([10, 4])
    """

    def __init__(self, scale: float = 4.0, tails: str = "gaussian", dof: float | None = None,
                 spherical: bool = False) -> None:
        super().__init__()
        if not (math.isfinite(float(scale)) and float(scale) > 0):
            raise ValueError(f"scale: expected a finite number > 0, got {scale}")
        _check_tails(tails, dof)
        self.scale, self.tails, self.dof, self.spherical = float(scale), tails, dof, spherical

    def forward(self, mean: torch.Tensor, cov: torch.Tensor, num: int,
                generator: torch.Generator | None = None) -> torch.Tensor:
        if self.spherical:
            cov = spherical_covariance(cov)
        return covariance_scaled_sample(mean, cov, num, self.scale, self.tails, self.dof,
                                        generator)

    def extra_repr(self) -> str:
        return (f"scale={self.scale}, tails={self.tails!r}, dof={self.dof}, "
                f"spherical={self.spherical}")
