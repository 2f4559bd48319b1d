"""Derivatives of a row-independent energy ``V(theta (P, D)) -> (P,)``: the value, gradient and
(Gauss–Newton or true) Hessian of every row, by the energy's own analytic Gauss–Newton
derivatives, autograd, or central finite differences (:func:`energy_derivatives`).

Example:
    >>> V = lambda x: (x ** 2).sum(-1)
    >>> v, g, H = energy_derivatives(V, torch.ones(3, 2, dtype=torch.float64), method="autograd")
    >>> H[0]
    tensor([[2., 0.],
            [0., 2.]], dtype=torch.float64)
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["DERIVATIVES", "HESSIANS", "energy_derivatives"]


def _autograd_value_grad(energy, x: torch.Tensor, create_graph: bool = False):
    x = x.detach().requires_grad_(True)
    with torch.enable_grad():
        v = energy(x)
        if not isinstance(v, torch.Tensor) or v.shape != x.shape[:1]:
            raise ValueError(f"energy: expected a ({x.shape[0]},) tensor")
        if not v.requires_grad:
            return v.detach(), None, x, v
        (g,) = torch.autograd.grad(v.sum(), x, create_graph=create_graph)
    return v, g, x, v


def _fd_hessian(energy, x: torch.Tensor, step: float, chunk: int = 8192) -> torch.Tensor:
    """Central finite-difference Hessian ``(P, D, D)`` of a row-independent energy."""
    P, D = x.shape
    h = float(step)
    eye = torch.eye(D, dtype=x.dtype, device=x.device) * h
    pairs = [(i, j) for i in range(D) for j in range(i + 1, D)]
    offs = [torch.zeros(D, dtype=x.dtype, device=x.device)]
    offs += [2 * eye[i] for i in range(D)] + [-2 * eye[i] for i in range(D)]
    for i, j in pairs:
        offs += [eye[i] + eye[j], eye[i] - eye[j], -eye[i] + eye[j], -eye[i] - eye[j]]
    O = torch.stack(offs)  # (Q, D)
    pts = (x[:, None] + O[None]).reshape(-1, D)
    with torch.no_grad():
        vals = torch.cat([energy(pts[s:s + chunk]) for s in range(0, pts.shape[0], chunk)])
    vals = vals.reshape(P, -1).to(x.dtype)
    f0 = vals[:, 0]
    H = torch.zeros(P, D, D, dtype=x.dtype, device=x.device)
    fp, fm = vals[:, 1:1 + D], vals[:, 1 + D:1 + 2 * D]
    H[:, range(D), range(D)] = (fp - 2 * f0[:, None] + fm) / (4 * h * h)
    q = 1 + 2 * D
    for n, (i, j) in enumerate(pairs):
        a, b, c, d = vals[:, q + 4 * n:q + 4 * n + 4].unbind(-1)
        H[:, i, j] = H[:, j, i] = (a - b - c + d) / (4 * h * h)
    return H


def energy_derivatives(energy, theta: torch.Tensor, hessian: bool = True,
                       method: str = "auto", fd_step: float | None = None,
                       gauss_newton: Callable | None = None):
    """Energy, gradient and (Gauss–Newton or true) Hessian of a row-independent energy.

    Args:
        energy: ``V(theta (P, D)) -> (P,)`` (a :class:`~torchmocap.likelihoods.FrameEnergy`
            or any callable).
        theta: ``(P, D)``.
        hessian: also compute ``H``.
        method: ``"gauss_newton"`` (the analytic derivatives ``gauss_newton``; an error
            without them), ``"autograd"`` (gradient and exact Hessian by double backward),
            ``"finite_difference"`` (autograd gradient when available, Hessian by central
            differences of ``V``) or ``"auto"`` (Gauss–Newton, else autograd, else finite
            differences).
        fd_step: finite-difference step (default ``1e-3`` in float64, ``1e-2`` otherwise).
        gauss_newton: the energy's analytic derivatives, ``fn(theta (P, D), hessian) -> (V,
            grad, H)`` (e.g. :meth:`~torchmocap.likelihoods.FrameEnergy.gauss_newton` of a
            likelihood that offers them), or None.

    Returns:
        ``V (P,)``, ``grad (P, D)`` (None when ``V`` is not differentiable) and
        ``H (P, D, D)`` (None when not asked).
    """
    if method not in DERIVATIVES:
        raise ValueError(f"method: expected one of {HESSIANS}, got {method!r}")
    step = fd_step if fd_step is not None else (1e-3 if theta.dtype == torch.float64
                                                 else 1e-2)
    return DERIVATIVES[method](energy, theta, hessian, step, gauss_newton)


def _gauss_newton(energy, theta, hessian, step, fn):
    """The analytic derivatives ``fn``, or None without them."""
    if fn is None:
        return None
    v, g, H = fn(theta.detach(), hessian)
    return v.detach(), g.detach(), None if H is None else H.detach()


def _gauss_newton_required(energy, theta, hessian, step, fn):
    out = _gauss_newton(energy, theta, hessian, step, fn)
    if out is None:
        raise ValueError("energy: Gauss-Newton derivatives need an energy that offers them "
                         "(a likelihood whose every active term has offers_gauss_newton, e.g. "
                         "Joints2DLikelihood)")
    return out


def _by_autograd(energy, theta, hessian, step, exact: bool, strict: bool):
    """Autograd gradient; Hessian by double backward (``exact``) or central differences. A
    non-differentiable energy is an error when ``strict``, else gets a difference Hessian."""
    P, D = theta.shape
    want_exact = hessian and exact
    v, g, x, vg = _autograd_value_grad(energy, theta, create_graph=want_exact)
    if g is None:
        if strict:
            raise ValueError("energy: output does not depend differentiably on theta")
        H = _fd_hessian(energy, theta.detach(), step) if hessian else None
        return v.detach(), None, H
    H = None
    if hessian:
        if want_exact and g.requires_grad:
            cols = []
            with torch.enable_grad():
                for d in range(D):
                    (c,) = torch.autograd.grad(g[:, d].sum(), x, retain_graph=d < D - 1,
                                               allow_unused=True)
                    cols.append(torch.zeros_like(theta) if c is None else c)
            H = torch.stack(cols, -1).detach()
            H = 0.5 * (H + H.transpose(-1, -2))
        elif want_exact:  # piecewise-linear in theta: the gradient is locally constant
            H = torch.zeros(P, D, D, dtype=theta.dtype, device=theta.device)
        else:
            H = _fd_hessian(energy, theta.detach(), step)
    return v.detach(), g.detach(), H


def _auto(energy, theta, hessian, step, fn):
    """Gauss–Newton where the energy offers it, else autograd (difference Hessian as the last
    resort for a non-differentiable energy)."""
    return (_gauss_newton(energy, theta, hessian, step, fn)
            or _by_autograd(energy, theta, hessian, step, exact=True, strict=False))


#: the derivative methods of :func:`energy_derivatives` by name, each called as
#: ``(energy, theta, hessian, fd_step, gauss_newton) -> (V, grad, H)``
DERIVATIVES = {
    "auto": _auto,
    "gauss_newton": _gauss_newton_required,
    "autograd": lambda e, t, h, s, fn: _by_autograd(e, t, h, s, exact=True, strict=True),
    "finite_difference": lambda e, t, h, s, fn: _by_autograd(e, t, h, s, exact=False,
                                                             strict=False),
}
HESSIANS = tuple(DERIVATIVES)


# ---------------------------------------------------------------------- local optimisation


HESSIANS = tuple(DERIVATIVES)
