"""Paden–Kahan subproblems and the decomposition of a rotation into three axis rotations.

Batched, differentiable solutions (Murray, Li & Sastry, ch. 3; Pons-Moll et al. 2010, §4.1):

* :func:`subproblem1` — ``rot(k, theta) p = q``;
* :func:`subproblem2` — ``rot(w1, t1) rot(w2, t2) p = q`` (two axes through the origin), two
  solutions;
* :func:`three_axis_decomposition` — ``rot(w1, t1) rot(w2, t2) rot(w3, t3) = R``, two solutions.

``rot(k, theta) = I + sin(theta) K + (1 - cos(theta)) K^2`` with ``K = hat(k)``; axes are unit
vectors through the origin, angles are radians. When no exact solution exists every function
returns the least-squares answer and clears the ``exact`` flag; it never returns NaN for finite
input. Degenerate configurations (a point on its rotation axis, parallel axes, gimbal lock) are
flagged and given a valid answer.

Example:
    >>> k = torch.tensor([0.0, 0.0, 1.0]); p = torch.tensor([1.0, 0.0, 0.0])
    >>> subproblem1(k, p, torch.tensor([0.0, 1.0, 0.0])).theta  # pi / 2
    tensor(1.5708)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchmocap.geometry._checks import check_last_dims

__all__ = [
    "Subproblem1Result",
    "Subproblem2Result",
    "ThreeAxisResult",
    "subproblem1",
    "subproblem2",
    "three_axis_decomposition",
    "orthogonal_three_axis_decomposition",
    "axes_are_orthogonal",
    "three_axis_rotation",
    "rotate_about_axis",
]


@dataclass
class Subproblem1Result:
    """Solution of ``rot(k, theta) p = q``.

    Attributes:
        theta: ``(*)`` angle in ``(-pi, pi]`` (least-squares optimum when not exact).
        exact: ``(*)`` bool, an exact solution exists (``|p|=|q|`` and ``k.p = k.q`` within tol).
        degenerate: ``(*)`` bool, ``p`` or ``q`` lies on the axis: every angle is equally good
            and ``theta`` is 0.
        residual: ``(*)`` ``|rot(k, theta) p - q|``.
    """

    theta: torch.Tensor
    exact: torch.Tensor
    degenerate: torch.Tensor
    residual: torch.Tensor


@dataclass
class Subproblem2Result:
    """Solutions of ``rot(w1, t1) rot(w2, t2) p = q``.

    Attributes:
        theta1, theta2: ``(*, 2)`` the two solutions (equal when the solution is unique,
            i.e. tangency, parallel axes or the least-squares case).
        exact: ``(*)`` bool, an exact solution exists (within tol).
        parallel: ``(*)`` bool, ``w1`` and ``w2`` are (anti)parallel: only ``t1 +- t2`` is
            determined; ``theta2`` is 0.
        degenerate: ``(*)`` bool, ``p`` lies on ``w2`` or ``q`` on ``w1`` (one angle is free and
            set to 0, or to ``default_theta1`` for the first axis).
        residual: ``(*, 2)`` ``|rot(w1, t1) rot(w2, t2) p - q|`` for each solution.
    """

    theta1: torch.Tensor
    theta2: torch.Tensor
    exact: torch.Tensor
    parallel: torch.Tensor
    degenerate: torch.Tensor
    residual: torch.Tensor


@dataclass
class ThreeAxisResult:
    """Solutions of ``rot(w1, t1) rot(w2, t2) rot(w3, t3) = R``.

    Attributes:
        angles: ``(*, 2, 3)`` two solutions ``(t1, t2, t3)``.
        exact: ``(*)`` bool, ``R`` is reachable with these axes (within tol).
        gimbal: ``(*)`` bool, gimbal lock (``R w3 = +-w1``): only ``t1 +- t3`` is determined;
            ``t1`` is set to ``default_theta1`` (0 unless given) and ``t3`` absorbs the rest.
        residual: ``(*, 2)`` geodesic angle (radians) between the reconstructed rotation and ``R``.
    """

    angles: torch.Tensor
    exact: torch.Tensor
    gimbal: torch.Tensor
    residual: torch.Tensor


def _tol(dtype: torch.dtype, tol: float | None) -> float:
    if tol is not None:
        return tol
    return 1e-9 if dtype == torch.float64 else 1e-4


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a, b = torch.broadcast_tensors(a, b)
    return torch.linalg.cross(a, b, dim=-1)


def _safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    """``sqrt(max(x, 0))`` with a zero (not NaN) gradient at and below 0."""
    pos = x > 0
    return torch.where(pos, torch.where(pos, x, torch.ones_like(x)).sqrt(), torch.zeros_like(x))


def _safe_atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``atan2`` that returns 0 with zero gradient at the origin (instead of NaN gradients)."""
    zero = (y == 0) & (x == 0)
    return torch.where(zero, torch.zeros_like(y), torch.atan2(y, torch.where(zero, 1.0, x)))


def rotate_about_axis(k: torch.Tensor, theta: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``rot(k, theta) v`` (Rodrigues on vectors): ``k`` ``(*, 3)`` unit, ``theta`` ``(*)``."""
    c = torch.cos(theta)[..., None]
    s = torch.sin(theta)[..., None]
    kv = _dot(k, v)[..., None]
    return c * v + s * _cross(k, v) + (1 - c) * kv * k


def three_axis_rotation(axes: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """``rot(w1, t1) rot(w2, t2) rot(w3, t3)``: ``axes`` ``(*, 3, 3)`` (rows = axes), ``angles``
    ``(*, 3)`` -> ``(*, 3, 3)``. Works for any number ``n`` of axes ``(*, n, 3)``/``(*, n)``."""
    from torchmocap.geometry.rotations import axis_angle_rotation

    Rs = axis_angle_rotation(axes, angles)
    out = Rs[..., 0, :, :]
    for i in range(1, Rs.shape[-3]):
        out = out @ Rs[..., i, :, :]
    return out


def subproblem1(
    k: torch.Tensor, p: torch.Tensor, q: torch.Tensor, tol: float | None = None
) -> Subproblem1Result:
    """Paden–Kahan subproblem 1: the angle ``theta`` with ``rot(k, theta) p = q``.

    ``theta = atan2(k.(p x q), p.q - (k.p)(k.q))`` — the least-squares optimum of
    ``|rot(k, theta) p - q|`` whether or not an exact solution exists.

    Args:
        k: ``(*, 3)`` unit axis through the origin.
        p, q: ``(*, 3)`` points (broadcast against ``k``).
        tol: absolute tolerance for the ``exact``/``degenerate`` flags (default ``1e-9`` in
            float64, ``1e-4`` otherwise), relative to ``max(1, |p|)``.
    Returns:
        :class:`Subproblem1Result` with ``(*)`` fields.
    """
    check_last_dims(k, (3,), "k")
    check_last_dims(p, (3,), "p")
    check_last_dims(q, (3,), "q")
    t = _tol(p.dtype, tol)
    kp, kq = _dot(k, p), _dot(k, q)
    pp = p - kp[..., None] * k
    qp = q - kq[..., None] * k
    y = _dot(k, _cross(pp, qp))
    x = _dot(pp, qp)
    theta = _safe_atan2(y, x)
    scale = torch.clamp(p.detach().norm(dim=-1), min=1.0)
    degenerate = (pp.detach().norm(dim=-1) <= t * scale) | (qp.detach().norm(dim=-1) <= t * scale)
    theta = torch.where(degenerate, torch.zeros_like(theta), theta)
    exact = ((p.norm(dim=-1) - q.norm(dim=-1)).abs() <= t * scale) & ((kp - kq).abs() <= t * scale)
    residual = (rotate_about_axis(k, theta, p) - q).norm(dim=-1)
    return Subproblem1Result(theta, exact.detach(), degenerate, residual)


def _sp1_angle(k: torch.Tensor, p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    kp, kq = _dot(k, p), _dot(k, q)
    pp = p - kp[..., None] * k
    qp = q - kq[..., None] * k
    return _safe_atan2(_dot(k, _cross(pp, qp)), _dot(pp, qp))


def _sp2_core(
    w1: torch.Tensor,
    w2: torch.Tensor,
    p: torch.Tensor,
    q: torch.Tensor,
    t: float,
    default_theta1: torch.Tensor | None,
) -> tuple[torch.Tensor, ...]:
    """Shared SP2 solver on unit directions; returns ``t1, t2 (*, 2)`` and flags ``(*)``."""
    pn = p.norm(dim=-1, keepdim=True)
    qn = q.norm(dim=-1, keepdim=True)
    ph = p / torch.where(pn > 0, pn, torch.ones_like(pn))
    qh = q / torch.where(qn > 0, qn, torch.ones_like(qn))
    d = _dot(w1, w2)
    n = _cross(w1, w2)
    n2 = _dot(n, n)
    parallel = n2 <= t
    den = torch.where(parallel, torch.ones_like(n2), n2)
    a = _dot(w1, qh)
    b = _dot(w2, ph)
    alpha = (a - d * b) / den
    beta = (b - d * a) / den
    z = alpha[..., None] * w1 + beta[..., None] * w2
    gamma2 = (1 - _dot(z, z)) / den
    meets = gamma2 >= -t
    gamma = _safe_sqrt(gamma2)
    sqn = torch.sqrt(den)
    # exact: c = z +- gamma n  (|n| = sqrt(n2))
    c_plus = z + gamma[..., None] * n
    c_minus = z - gamma[..., None] * n
    # least squares: the point of the circle of p about w2 in the plane span(w1, w2) whose
    # cosine to w1 is closest to w1.q (the circles' closest directions lie in that plane)
    u2 = (w1 - d[..., None] * w2) / sqn[..., None]
    r2 = _safe_sqrt(1 - b * b)
    x_hi = b[..., None] * w2 + r2[..., None] * u2
    x_lo = b[..., None] * w2 - r2[..., None] * u2
    pick_hi = (_dot(w1, x_hi) - a).abs() <= (_dot(w1, x_lo) - a).abs()
    c_ls = torch.where(pick_hi[..., None], x_hi, x_lo)
    c = torch.stack(
        [torch.where(meets[..., None], c_plus, c_ls), torch.where(meets[..., None], c_minus, c_ls)],
        dim=-2,
    )  # (*, 2, 3)
    w1e, w2e = w1[..., None, :], w2[..., None, :]
    t2 = _sp1_angle(w2e, ph[..., None, :], c)
    t1 = _sp1_angle(w1e, c, qh[..., None, :])
    # degenerate: q on w1 (t1 free) or p on w2 (t2 free). The angle is forced only when the
    # generic formula has lost its accuracy (sin^2 of the angle to the axis ~ machine eps);
    # forcing it for larger angles would leave a residual of that angle.
    eps = 16 * torch.finfo(p.dtype).eps
    q_on_w1 = _dot(_cross(w1, qh), _cross(w1, qh)) <= eps
    p_on_w2 = _dot(_cross(w2, ph), _cross(w2, ph)) <= eps
    if default_theta1 is None:
        dt1 = torch.zeros_like(t1)
    else:
        dt1 = default_theta1[..., None].to(t1).expand_as(t1)
    t1 = torch.where(q_on_w1[..., None], dt1, t1)
    t2 = torch.where(p_on_w2[..., None], torch.zeros_like(t2), t2)
    # parallel axes: rot(w1, t1 + sign(d) t2); solve for the sum, t2 = 0
    tpar = _sp1_angle(w1, ph, qh)[..., None].expand_as(t1)
    t1 = torch.where(parallel[..., None], tpar, t1)
    t2 = torch.where(parallel[..., None], torch.zeros_like(t2), t2)
    same_norm = (pn - qn).squeeze(-1).abs() <= t * torch.clamp(pn.squeeze(-1), min=1.0)
    exact = (meets | parallel) & same_norm
    if bool(parallel.any()):
        exact_par = (a - _dot(w1, ph)).abs() <= t
        exact = torch.where(parallel, exact_par & same_norm, exact)
    degenerate = (q_on_w1 | p_on_w2) & ~parallel
    return t1, t2, exact, parallel, degenerate


def subproblem2(
    w1: torch.Tensor,
    w2: torch.Tensor,
    p: torch.Tensor,
    q: torch.Tensor,
    tol: float | None = None,
    default_theta1: torch.Tensor | None = None,
) -> Subproblem2Result:
    """Paden–Kahan subproblem 2: ``rot(w1, t1) rot(w2, t2) p = q`` for two axes through the origin.

    The intermediate point ``c = rot(w2, t2) p = rot(w1, -t1) q`` lies on both circles; it is
    ``c = alpha w1 + beta w2 +- gamma (w1 x w2)`` (Murray–Li–Sastry), then two subproblem-1
    solutions give the angles. Computed on the directions ``p/|p|``, ``q/|q|``, so when the
    circles do not meet (or ``|p| != |q|``) the returned pair is the least-squares optimum of
    ``|rot(w1,t1) rot(w2,t2) p - q|`` (closest directions lie in ``span(w1, w2)``) and ``exact``
    is False. Parallel axes are special-cased (no division by ``|w1 x w2|``).

    Args:
        w1, w2: ``(*, 3)`` unit axes.
        p, q: ``(*, 3)`` points.
        tol: flag tolerance (see :func:`subproblem1`).
        default_theta1: ``(*)`` value of ``t1`` where it is undetermined (``q`` on ``w1``);
            0 when omitted.
    Returns:
        :class:`Subproblem2Result`; ``theta1``, ``theta2``, ``residual`` are ``(*, 2)``.

    Example:
        >>> ez, ey = torch.tensor([0., 0., 1.]), torch.tensor([0., 1., 0.])
        >>> subproblem2(ez, ey, torch.tensor([1., 0, 0]), torch.tensor([0., 0.6, 0.8])).theta1.shape
        torch.Size([2])
    """
    for x, name in ((w1, "w1"), (w2, "w2"), (p, "p"), (q, "q")):
        check_last_dims(x, (3,), name)
    w1, w2, p, q = torch.broadcast_tensors(w1, w2, p, q)
    t = _tol(p.dtype, tol)
    t1, t2, exact, parallel, degenerate = _sp2_core(w1, w2, p, q, t, default_theta1)
    pe = p[..., None, :]
    x = rotate_about_axis(w1[..., None, :], t1, rotate_about_axis(w2[..., None, :], t2, pe))
    residual = (x - q[..., None, :]).norm(dim=-1)
    return Subproblem2Result(t1, t2, exact.detach(), parallel, degenerate, residual)


def three_axis_decomposition(
    R: torch.Tensor, w1: torch.Tensor, w2: torch.Tensor, w3: torch.Tensor,
    tol: float | None = None, default_theta1: torch.Tensor | None = None,
    compute_residual: bool = True,
) -> ThreeAxisResult:
    """Angles with ``rot(w1, t1) rot(w2, t2) rot(w3, t3) = R`` (Pons-Moll eqs. 12–14).

    Applies both sides to ``p = w3`` (a point on the third axis) to get subproblem 2
    ``rot(w1,t1) rot(w2,t2) w3 = R w3`` for ``(t1, t2)``; then ``M = rot(w2,-t2) rot(w1,-t1) R``
    is a rotation about ``w3`` and ``t3 = atan2(w3.vee(M), (tr M - w3.M w3) / 2)``.
    With ``w2`` orthogonal to ``w1`` and ``w3`` every ``R`` is reachable; otherwise unreachable
    ``R`` get the least-squares ``(t1, t2)`` and ``exact = False``. Gimbal lock
    (``R w3 = +-w1``) is flagged and resolved with ``t1 = default_theta1`` (0 if omitted).

    Args:
        R: ``(*, 3, 3)`` rotation matrices.
        w1, w2, w3: ``(*, 3)`` unit axes (broadcast against ``R``'s batch dims).
        tol: flag tolerance (default ``1e-9`` float64, ``1e-4`` otherwise).
        default_theta1: ``(*)`` value of ``t1`` under gimbal lock (e.g. the previous pose).
        compute_residual: also compute ``residual`` (a little extra work); else it is empty.
    Returns:
        :class:`ThreeAxisResult`, ``angles`` ``(*, 2, 3)``.

    Example:
        >>> ex, ey, ez = torch.eye(3)
        >>> three_axis_decomposition(torch.eye(3), ez, ey, ex).angles.shape
        torch.Size([2, 3])
    """
    check_last_dims(R, (3, 3), "R")
    for x, name in ((w1, "w1"), (w2, "w2"), (w3, "w3")):
        check_last_dims(x, (3,), name)
    batch = torch.broadcast_shapes(R.shape[:-2], w1.shape[:-1], w2.shape[:-1], w3.shape[:-1])
    R = R.expand(*batch, 3, 3)
    w1, w2, w3 = (w.expand(*batch, 3) for w in (w1, w2, w3))
    t = _tol(R.dtype, tol)
    q = (R @ w3[..., None]).squeeze(-1)
    t1, t2, exact, _parallel, degenerate = _sp2_core(w1, w2, w3, q, t, default_theta1)
    wq = _cross(w1, q)
    gimbal = _dot(wq, wq) <= t
    # t3 from M = rot(w2, -t2) rot(w1, -t1) R, applied column-wise via Rodrigues
    Re = R[..., None, :, :].transpose(-1, -2)  # rows = columns of R, (*, 1, 3, 3)
    w1e = w1[..., None, None, :]
    w2e = w2[..., None, None, :]
    A = rotate_about_axis(w1e, -t1[..., None], Re)
    Mt = rotate_about_axis(w2e, -t2[..., None], A)  # (*, 2, 3, 3) rows = columns of M
    M = Mt.transpose(-1, -2)
    w3e = w3[..., None, :]
    skew = torch.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]],
        dim=-1,
    )
    s3 = 0.5 * _dot(w3e, skew)
    trace = M.diagonal(dim1=-2, dim2=-1).sum(-1)
    c3 = 0.5 * (trace - _dot(w3e, (M @ w3e[..., None]).squeeze(-1)))
    t3 = _safe_atan2(s3, c3)
    angles = torch.stack([t1, t2, t3], dim=-1)
    if compute_residual:
        axes = torch.stack([w1, w2, w3], dim=-2)[..., None, :, :]
        Rrec = three_axis_rotation(axes, angles)
        Mr = Rrec.transpose(-1, -2) @ R[..., None, :, :]
        sk = torch.stack(
            [Mr[..., 2, 1] - Mr[..., 1, 2], Mr[..., 0, 2] - Mr[..., 2, 0],
             Mr[..., 1, 0] - Mr[..., 0, 1]], dim=-1,
        )
        residual = torch.atan2(0.5 * sk.norm(dim=-1),
                               0.5 * (Mr.diagonal(dim1=-2, dim2=-1).sum(-1) - 1))
    else:
        residual = angles.new_empty(0)
    del degenerate
    return ThreeAxisResult(angles, exact.detach(), gimbal.detach(), residual)


def orthogonal_three_axis_decomposition(
    R: torch.Tensor,
    axes: torch.Tensor,
    default_theta1: torch.Tensor | None = None,
    tol: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form :func:`three_axis_decomposition` for three mutually orthogonal axes.

    With ``e1 = w1``, ``e2 = w2``, ``e3 = w1 x w2 = h w3`` (``h = +-1``) and ``M = E^T R E``
    (``E = [e1 e2 e3]``) the problem is ``Rx(a) Ry(b) Rz(c) = M``:
    ``a = atan2(-M12, M22)``, ``b = atan2(M02, cos a M22 - sin a M12)``,
    ``c = atan2(cos a M10 + sin a M20, cos a M11 + sin a M21)``; ``(t1, t2, t3) = (a, b, h c)``.
    The second solution is ``(a + pi, pi - b, c + pi)`` (wrapped to ``(-pi, pi]``). ``b`` and ``c``
    are computed *given* ``a``, so the gimbal case (``M12 = M22 = 0``) needs no special branch:
    ``a = default_theta1`` (0 if omitted) there and the result is still exact. About 10x fewer
    operations than the general solver; every rotation is reachable.

    Args:
        R: ``(*, 3, 3)`` rotations.
        axes: ``(*, 3, 3)`` rows ``w1, w2, w3``, mutually orthogonal unit vectors (not checked
            here; :func:`axes_are_orthogonal` checks).
        default_theta1: ``(*)`` value of ``t1`` under gimbal lock.
        tol: gimbal flag tolerance on ``M12^2 + M22^2`` (default ``1e-9`` float64, ``1e-4``).
    Returns:
        ``angles (*, 2, 3)`` and ``gimbal (*)`` bool.
    """
    check_last_dims(R, (3, 3), "R")
    check_last_dims(axes, (3, 3), "axes")
    t = _tol(R.dtype, tol)
    w1, w2, w3 = axes.unbind(-2)
    e3 = _cross(w1, w2)
    h = _dot(e3, w3)  # +-1
    E = torch.stack([w1, w2, e3], dim=-1)  # columns
    M = E.transpose(-1, -2) @ R @ E
    m12, m22 = M[..., 1, 2], M[..., 2, 2]
    gimbal = (m12 * m12 + m22 * m22) <= t
    lock = (m12 * m12 + m22 * m22) <= (16 * torch.finfo(R.dtype).eps) ** 2
    a = _safe_atan2(-m12, m22)
    if default_theta1 is not None:
        a = torch.where(lock, default_theta1.to(a), a)
    ca, sa = torch.cos(a), torch.sin(a)
    b = torch.atan2(M[..., 0, 2], ca * m22 - sa * m12)
    c = torch.atan2(ca * M[..., 1, 0] + sa * M[..., 2, 0], ca * M[..., 1, 1] + sa * M[..., 2, 1])
    pi = math.pi
    a2 = torch.where(a > 0, a - pi, a + pi)
    b2 = torch.where(b >= 0, pi - b, -pi - b)
    c2 = torch.where(c > 0, c - pi, c + pi)
    angles = torch.stack(
        [torch.stack([a, b, h * c], -1), torch.stack([a2, b2, h * c2], -1)], dim=-2
    )
    return angles, gimbal


def axes_are_orthogonal(axes: torch.Tensor, tol: float = 1e-6) -> bool:
    """True when the rows of every ``(*, 3, 3)`` ``axes`` are mutually orthogonal unit vectors."""
    G = axes @ axes.transpose(-1, -2)
    return bool((G - torch.eye(3, dtype=axes.dtype, device=axes.device)).abs().max() <= tol)
