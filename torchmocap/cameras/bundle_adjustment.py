"""Refining a rig from the subject's own 2D detections: bundle adjustment without a board.

:func:`bundle_adjust` refines the chosen parameter groups of every camera
(:mod:`torchmocap.cameras.rig_parameters`; per-camera time offsets among them) together with
free 3D points, one per frame and keypoint, started at the confidence-weighted DLT of the
detections (:func:`~torchmocap.cameras.triangulate_dlt`). The objective is

``½ Σ w ρ(‖r‖²) / σ² + ½ Σ (z / width)²``

(:func:`~torchmocap.cameras.reprojection.reprojection_loss`: robust loss ``ρ``, confidence
weights ``w``, the detections' noise ``σ``; priors :class:`~torchmocap.cameras.RigPriors`), in
the gauge's null space (:mod:`torchmocap.cameras.rig_gauge`).

Solver: Levenberg–Marquardt with Marquardt's scaling (``H + λ diag H``), the robust loss by
iteratively reweighted least squares (weights ``w ρ'`` at each linearisation; a step is
accepted only if the robust objective falls). The points are eliminated by the Schur
complement: without time offsets every point is its own 3×3 block (batched over frames and
keypoints); with time offsets a camera sees the interpolated trajectory, which couples the
frames of a keypoint, and each keypoint's trajectory is one ``3T × 3T`` block (memory
``K (3T)²``: refine on a range of a few hundred frames). The camera system is dense (its
parameters are few). Jacobians come from forward-mode differentiation of the same projection
(:func:`~torchmocap.cameras.reprojection.refinement_pixels`). Everything runs in float64.

Uncertainty: at the solution the reduced camera matrix ``S = H_cc − H_cp H_pp⁻¹ H_pc`` (the
Gauss–Newton ``JᵀWJ`` with the points marginalised, priors included, IRLS weights, residuals
whitened by the noise σ̂ measured at the solution) gives the covariance ``S⁻¹`` of the refined
parameters; the report lists each one's marginal standard deviation and flags those the data
did not determine (posterior std above half its prior width: the prior, not the subject, set
it). Correlations of the detections (a detector's bias on a keypoint over frames) are not in
the model: the standard deviations are a lower bound, and two refinements on different frames
that disagree by more than them say so.

Shapes: ``T`` frames, ``C`` cameras, ``K`` keypoints.

Example:
    >>> from torchmocap.cameras import make_ring_rig
    >>> rig = make_ring_rig(3, image_size=(640, 480)).double()
    >>> g = torch.Generator().manual_seed(0)
    >>> X = torch.rand(8, 10, 3, generator=g, dtype=torch.float64) + torch.tensor([-.5, -.5, .5])
    >>> uv = rig.project(X)[0]                                             # (T, C, K, 2)
    >>> det = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    >>> res = bundle_adjust(det, rig, groups=("rotation",), noise_px=1.0)
    >>> res.converged, res.rig.num_cameras, res.points.shape
    (True, 3, torch.Size([8, 10, 3]))
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor
from torch.func import jvp

from torchmocap.cameras.reprojection import (
    RobustLoss,
    interpolation_weights,
    refinement_pixels,
)
from torchmocap.cameras.rig import CameraRig
from torchmocap.cameras.rig_gauge import check_gauge
from torchmocap.cameras.rig_parameters import (
    DEFAULT_GROUPS,
    NUM_VALUES,
    PARAMETER_NAMES,
    RefinementError,
    RigParametrization,
    apply_rig_parameters,
)
from torchmocap.cameras.rig_priors import RigPriors
from torchmocap.cameras.triangulation import triangulate_dlt

__all__ = ["BundleAdjustmentResult", "bundle_adjust", "check_frames"]

#: median of the distance of a 2D isotropic Gaussian of unit std (Rayleigh): sqrt(2 ln 2)
_RAYLEIGH_MEDIAN = math.sqrt(2 * math.log(2))
#: posterior std above this fraction of the prior width: "determined by the prior"
PRIOR_DOMINATED = 0.5
#: the measured noise has settled when it changes by less than this fraction between rounds
NOISE_TOLERANCE = 0.02
#: solves with a re-measured noise at most
MAX_NOISE_ROUNDS = 5


@dataclass
class BundleAdjustmentResult:
    """What :func:`bundle_adjust` found.

    Attributes:
        rig: the refined :class:`~torchmocap.cameras.CameraRig` (the given rig's dtype; image
            sizes and names kept). It applies to every frame of the sequence, not only the
            refined ones.
        values: ``(C, 13)`` float64 refined values
            (:data:`~torchmocap.cameras.rig_parameters.PARAMETER_NAMES`).
        time_offsets: ``(C,)`` frames: camera ``c``'s frame ``t`` shows the subject at
            ``t + δ_c`` (zeros unless ``time_offset`` was refined).
        points: ``(T, K, 3)`` refined 3D points of the refined frames (NaN: not refined).
        initial_points: ``(T, K, 3)`` their DLT start.
        frames: the refined frames (indices into the given detections).
        parametrization: the :class:`~torchmocap.cameras.rig_parameters.RigParametrization`.
        covariance: ``(C·13, C·13)`` covariance of the values (zero rows where not refined).
        std: ``(C, 13)`` marginal standard deviations (NaN: not refined).
        prior_width: ``(C, 13)`` prior widths (inf: no prior; NaN: not refined).
        residual_px_before, residual_px_after: ``(C,)`` median reprojection distance of the
            used detections, with the DLT points in the given rig / the refined points in the
            refined rig.
        noise_px: the σ of the objective and of the covariance (given, or measured at the
            solution).
        noise_rounds: solves run (more than one while a measured σ settles).
        iterations: Levenberg–Marquardt iterations run (accepted or not).
        cost_initial, cost_final: the objective at the start and at the solution.
        converged: the relative decrease fell below ``tolerance`` (or no step could lower the
            objective any more).
        message: why the solver stopped.
        num_detections: detections used (per camera: ``detections_per_camera``).
        settings: the settings, JSON-ready.
    """

    rig: CameraRig
    values: Tensor
    time_offsets: Tensor
    points: Tensor
    initial_points: Tensor
    frames: range
    parametrization: RigParametrization
    covariance: Tensor
    std: Tensor
    prior_width: Tensor
    residual_px_before: Tensor
    residual_px_after: Tensor
    noise_px: float
    noise_rounds: int
    iterations: int
    cost_initial: float
    cost_final: float
    converged: bool
    message: str
    num_detections: int
    detections_per_camera: list[int] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)

    def poorly_determined(self) -> list[str]:
        """Names ``"<camera>.<value>"`` of refined values the data did not determine: their
        posterior std exceeds :data:`PRIOR_DOMINATED` × their prior width (the prior, not the
        subject, held them), or, without a prior, that fraction of the default prior width
        (:class:`~torchmocap.cameras.RigPriors`: 5°, 0.25 m, 5 %, 20 px, 0.05, 2 frames). A
        shared focal scale is named ``log_f``."""
        shared = "focal" in self.parametrization.groups
        default = RigPriors().value_widths()
        out = []
        for c, name in enumerate(self.rig.names):
            for v in range(NUM_VALUES):
                if shared and v == 7:
                    continue
                s, w = float(self.std[c, v]), float(self.prior_width[c, v])
                if not math.isfinite(w):
                    w = default[v]
                if math.isfinite(s) and s > PRIOR_DOMINATED * w:
                    label = "log_f" if shared and v == 6 else PARAMETER_NAMES[v]
                    out.append(f"{name}.{label}")
        return out

    def correlation(self) -> Tensor:
        """``(C·13, C·13)`` correlation matrix of the values (NaN where not refined)."""
        d = self.covariance.diagonal().sqrt()
        return self.covariance / (d[:, None] * d[None, :])

    def report(self) -> dict[str, Any]:
        """JSON-ready per-camera report (:func:`~torchmocap.cameras.refinement_report`)."""
        from torchmocap.cameras.calibration_report import refinement_report

        return refinement_report(self)

    def markdown(self) -> str:
        """The report as a markdown table (:func:`~torchmocap.cameras.report_markdown`)."""
        from torchmocap.cameras.calibration_report import report_markdown

        return report_markdown(self.report())


def check_frames(frames, num_frames: int, name: str = "frames") -> range:
    """``frames`` (None, ``(start, stop)`` or a step-1 ``range``) as a range inside
    ``0 .. num_frames``; else a :class:`RefinementError` naming ``name``."""
    if frames is None:
        return range(num_frames)
    if isinstance(frames, range):
        if frames.step != 1:
            raise RefinementError(f"{name}: expected consecutive frames (step 1), got {frames}")
        start, stop = frames.start, frames.stop
    else:
        try:
            start, stop = frames
        except (TypeError, ValueError):
            raise RefinementError(f"{name}: expected (start, stop) or a range, got "
                                  f"{frames!r}") from None
    for v in (start, stop):
        if isinstance(v, bool) or not isinstance(v, int):
            raise RefinementError(f"{name}: expected whole frame indices, got {frames!r}")
    if not 0 <= start < stop <= num_frames:
        raise RefinementError(f"{name}: frames {start}..{stop - 1} are not inside the "
                              f"sequence's {num_frames} frames (0..{num_frames - 1})")
    return range(start, stop)


def _number(value, name: str, what: str, ok) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not math.isfinite(value) or not ok(value):
        raise RefinementError(f"{name}: expected {what}, got {value!r}")
    return float(value)


def _copy_rig(rig: CameraRig, device) -> CameraRig:
    return CameraRig(rig.K.to(device), rig.R.to(device), rig.t.to(device),
                     rig.image_size.to(device), rig.dist.to(device), rig.names)


def _fill_in_time(X: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Gaps of each keypoint's trajectory ``X (T, K, 3)`` filled linearly between its valid
    frames (held at the ends); keypoints with fewer than 2 valid frames are dropped."""
    T, K, _ = X.shape
    out = torch.zeros_like(X)
    keep = valid.sum(0) >= 2
    frames = torch.arange(T, dtype=X.dtype, device=X.device)
    for k in keep.nonzero().flatten().tolist():
        idx = valid[:, k].nonzero().flatten()
        f = idx.to(X.dtype)
        j = torch.searchsorted(f, frames).clamp(1, len(f) - 1)
        f0, f1 = f[j - 1], f[j]
        u = ((frames - f0) / (f1 - f0)).clamp(0, 1)[:, None]
        out[:, k] = (1 - u) * X[idx[j - 1], k] + u * X[idx[j], k]
    return out, keep


class _Problem:
    """The bundle adjustment's data, residuals and normal equations (float64)."""

    def __init__(self, par: RigParametrization, uv: Tensor, weight: Tensor, loss: RobustLoss,
                 widths: Tensor, temporal: bool, smoothing: float = 0.0) -> None:
        self.par, self.uv, self.weight, self.loss = par, uv, weight, loss
        self.widths = widths
        #: weight 1 / σ_a² of the trajectory's second differences (m/frame²; 0 = none)
        self.smoothing = smoothing
        self.temporal = temporal
        self.T, self.C, self.K = uv.shape[:3]
        self.M = par.value_map()  # (C, 13, n_y)
        rows = self.M.abs().sum((0, 2)) > 0
        self.active = [v for v in range(NUM_VALUES) if bool(rows[v]) and v != 12]
        self.frame_times = torch.arange(self.T, dtype=uv.dtype, device=uv.device)

    # ----------------------------------------------------------------- forward model
    def taps(self, values: Tensor):
        times = self.frame_times[None, :] + values[:, 12:13]
        return interpolation_weights(times, self.T)  # (C, T, 4) each

    def observed(self, X: Tensor, taps) -> Tensor:
        """The points each camera sees: ``(C, T, K, 3)`` (temporal) or ``X``."""
        if not self.temporal:
            return X
        frames, w, _ = taps
        return (X[frames] * w[..., None, None]).sum(-3)

    def pixels(self, values: Tensor, X_obs: Tensor) -> Tensor:
        K, R, t, dist = apply_rig_parameters(values, self.par.K, self.par.R, self.par.t,
                                             self.par.dist)
        return refinement_pixels(X_obs, K, R, t, dist, per_camera=self.temporal)

    def residuals(self, y: Tensor, X: Tensor) -> Tensor:
        values = self.par.values(y)
        taps = self.taps(values) if self.temporal else None
        return self.pixels(values, self.observed(X, taps)) - self.uv

    def acceleration(self, X: Tensor) -> Tensor:
        """Second differences of the trajectories ``(T − 2, K, 3)``."""
        return X[2:] - 2 * X[1:-1] + X[:-2]

    def cost(self, y: Tensor, X: Tensor, r: Tensor, sigma: float) -> float:
        s = (r * r).sum(-1)
        used = self.weight > 0
        data = 0.5 * (self.weight * self.loss.rho(torch.where(used, s, torch.zeros_like(s)))
                      ).sum() / sigma ** 2
        z = self.par.basis @ y
        total = data + 0.5 * ((z / self.widths) ** 2).sum()
        if self.smoothing:
            total = total + 0.5 * self.smoothing * (self.acceleration(X) ** 2).sum()
        return float(total)

    # ----------------------------------------------------------------- linearisation
    def linearise(self, y: Tensor, X: Tensor):
        """Residuals and Jacobians: ``r (T, C, K, 2)``, ``J_y (T, C, K, 2, n_y)``,
        ``J_X (T, C, K, 2, 3)`` (in the observed point) and the taps."""
        values = self.par.values(y)
        taps = self.taps(values) if self.temporal else None
        X_obs = self.observed(X, taps)
        pix = self.pixels(values, X_obs)
        cols = []
        for v in self.active:
            tangent = torch.zeros_like(values)
            tangent[:, v] = 1.0
            cols.append(jvp(lambda vv: self.pixels(vv, X_obs), (values,), (tangent,))[1])
        J_X = []
        for a in range(3):
            tangent = torch.zeros_like(X_obs)
            tangent[..., a] = 1.0
            J_X.append(jvp(lambda xx: self.pixels(values, xx), (X_obs,), (tangent,))[1])
        J_X = torch.stack(J_X, -1)  # (T, C, K, 2, 3)
        idx = list(self.active)
        if self.temporal and "time_offset" in self.par.groups:
            frames, _, dw = taps
            dX = (X[frames] * dw[..., None, None]).sum(-3)  # (C, T, K, 3) d X_obs / d delta
            cols.append(torch.einsum("tckai,ctki->tcka", J_X, dX))
            idx.append(12)
        J_v = torch.stack(cols, -1)  # (T, C, K, 2, n_active)
        J_y = torch.einsum("tckap,cpy->tckay", J_v, self.M[:, idx, :])
        return pix - self.uv, J_y, J_X, taps

    def normal_equations(self, y: Tensor, X: Tensor, r: Tensor, J_y: Tensor, J_X: Tensor,
                         taps, sigma: float):
        """``H_yy, g_y`` (priors included), and the point blocks ``H_pp (G, m, m)``,
        ``H_py (G, m, n_y)``, ``g_p (G, m)``."""
        s = (r * r).sum(-1)
        W = self.weight * self.loss.weight(torch.where(self.weight > 0, s, torch.zeros_like(s)))
        W = W / sigma ** 2
        H_yy = torch.einsum("tckay,tck,tckaz->yz", J_y, W, J_y)
        g_y = torch.einsum("tckay,tck,tcka->y", J_y, W, r)
        B = self.par.basis
        inv_w2 = 1.0 / self.widths ** 2
        H_yy = H_yy + B.T @ (inv_w2[:, None] * B)
        g_y = g_y + B.T @ (inv_w2 * (B @ y))
        if not self.temporal:
            H_pp = torch.einsum("tckai,tck,tckaj->tkij", J_X, W, J_X).reshape(-1, 3, 3)
            H_py = torch.einsum("tckai,tck,tckay->tkiy", J_X, W, J_y).reshape(
                -1, 3, J_y.shape[-1])
            g_p = torch.einsum("tckai,tck,tcka->tki", J_X, W, r).reshape(-1, 3)
            return H_yy, g_y, H_pp, H_py, g_p
        frames, w, _ = taps  # (C, T, 4)
        T, C, K, n = self.T, self.C, self.K, J_y.shape[-1]
        A = torch.einsum("tckai,tck,tckaj->ctkij", J_X, W, J_X).reshape(C, T, K, 1, 9)
        E = torch.einsum("tckai,tck,tckay->ctkiy", J_X, W, J_y)
        e = torch.einsum("tckai,tck,tcka->ctki", J_X, W, r)
        pair = (frames[..., :, None] * T + frames[..., None, :]).reshape(-1)  # (C T 16)
        coef = (w[..., :, None] * w[..., None, :]).reshape(C, T, 1, 16, 1)
        src = (coef * A).permute(2, 0, 1, 3, 4).reshape(K, -1, 9)
        H_pp = torch.zeros(K, T * T, 9, dtype=r.dtype, device=r.device).index_add_(1, pair, src)
        H_pp = H_pp.reshape(K, T, T, 3, 3).permute(0, 1, 3, 2, 4).reshape(K, 3 * T, 3 * T)
        single = frames.reshape(-1)  # (C T 4)
        src = (w.reshape(C, T, 1, 4, 1, 1) * E.unsqueeze(3)).permute(2, 0, 1, 3, 4, 5)
        H_py = torch.zeros(K, T, 3, n, dtype=r.dtype, device=r.device).index_add_(
            1, single, src.reshape(K, -1, 3, n)).reshape(K, 3 * T, n)
        src = (w.reshape(C, T, 1, 4, 1) * e.unsqueeze(3)).permute(2, 0, 1, 3, 4)
        g_p = torch.zeros(K, T, 3, dtype=r.dtype, device=r.device).index_add_(
            1, single, src.reshape(K, -1, 3)).reshape(K, 3 * T)
        if self.smoothing:
            D = torch.zeros(T - 2, T, dtype=r.dtype, device=r.device)
            i = torch.arange(T - 2, device=r.device)
            D[i, i], D[i, i + 1], D[i, i + 2] = 1.0, -2.0, 1.0
            DtD = self.smoothing * (D.T @ D)
            eye = torch.eye(3, dtype=r.dtype, device=r.device)
            H_pp = H_pp + torch.kron(DtD, eye)
            g_p = g_p + torch.einsum("fg,gki->kfi", DtD, X).reshape(K, 3 * T)
        return H_yy, g_y, H_pp, H_py, g_p

    def point_step(self, dp: Tensor) -> Tensor:
        """A point step in block layout as ``(T, K, 3)``."""
        if not self.temporal:
            return dp.reshape(self.T, self.K, 3)
        return dp.reshape(self.K, self.T, 3).transpose(0, 1)


def _damped_blocks(H: Tensor, lam: float) -> Tensor:
    """``H + λ diag H`` plus a tiny ridge (1 on the diagonal of a block that sees nothing)."""
    d = H.diagonal(dim1=-2, dim2=-1)
    scale = d.mean(-1, keepdim=True)
    ridge = torch.where(scale > 0, 1e-9 * scale, torch.ones_like(scale))
    return H + torch.diag_embed(lam * d + ridge.expand_as(d))


def _reduced_system(H_yy, g_y, H_pp, H_py, g_p, lam: float):
    """The Schur complement: ``S, b`` and the factor of the damped point blocks."""
    L, info = torch.linalg.cholesky_ex(_damped_blocks(H_pp, lam))
    if bool((info != 0).any()):
        raise RefinementError("the point blocks of the normal equations are not positive "
                              "definite (a point seen by no camera?)")
    Hi_py = torch.cholesky_solve(H_py, L)  # (G, m, n)
    Hi_gp = torch.cholesky_solve(g_p.unsqueeze(-1), L).squeeze(-1)  # (G, m)
    d = H_yy.diagonal()
    S = H_yy + torch.diag(lam * d + 1e-12 * d.abs().max().clamp_min(1e-300))
    S = S - torch.einsum("gmy,gmz->yz", H_py, Hi_py)
    b = g_y - torch.einsum("gmy,gm->y", H_py, Hi_gp)
    return S, b, Hi_py, Hi_gp


def _solve(S: Tensor, b: Tensor) -> Tensor:
    L, info = torch.linalg.cholesky_ex(S)
    if int(info) == 0:
        return torch.cholesky_solve(b[:, None], L)[:, 0]
    return torch.linalg.lstsq(S, b[:, None]).solution[:, 0]


def _median_per_camera(r: Tensor, used: Tensor) -> Tensor:
    d = r.norm(dim=-1)  # (T, C, K)
    out = []
    for c in range(d.shape[1]):
        vals = d[:, c][used[:, c]]
        out.append(vals.median() if vals.numel() else d.new_tensor(float("nan")))
    return torch.stack(out)


def _sigma(r: Tensor, used: Tensor) -> float:
    d = r.norm(dim=-1)[used]
    return max(float(d.median()) / _RAYLEIGH_MEDIAN, 1e-2)


def _levenberg_marquardt(prob: _Problem, y: Tensor, X: Tensor, sigma: float, max_iterations: int,
                         tolerance: float, max_time_offset: float | None):
    """Damped Gauss–Newton on the Schur-reduced system: ``y, X, iterations, converged,
    message``."""
    r = prob.residuals(y, X)
    cost = prob.cost(y, X, r, sigma)
    lam = 1e-3
    nu = 2.0
    converged, message, it = False, "maximum iterations reached", 0
    relinearise = True
    system = None
    while it < max_iterations:
        it += 1
        if relinearise:
            r, J_y, J_X, taps = prob.linearise(y, X)
            system = prob.normal_equations(y, X, r, J_y, J_X, taps, sigma)
        S, b, Hi_py, Hi_gp = _reduced_system(*system, lam)
        dy = -_solve(S, b)
        dp = -(Hi_gp + torch.einsum("gmy,y->gm", Hi_py, dy))
        y_new, X_new = y + dy, X + prob.point_step(dp)
        ok = True
        if max_time_offset is not None:
            ok = bool((prob.par.values(y_new)[:, 12].abs() <= max_time_offset).all())
        new_cost = prob.cost(y_new, X_new, prob.residuals(y_new, X_new), sigma) if ok \
            else math.inf
        if math.isfinite(new_cost) and new_cost < cost:
            decrease = (cost - new_cost) / max(cost, 1e-300)
            y, X, cost = y_new, X_new, new_cost
            lam, nu = max(lam / 3.0, 1e-12), 2.0
            relinearise = True
            if decrease < tolerance:
                converged, message = True, f"relative decrease {decrease:.2e} < tolerance"
                break
        else:
            lam, nu = lam * nu, nu * 2.0
            relinearise = False
            if lam > 1e10:
                converged, message = True, "no step lowers the objective (a minimum)"
                break
    return y, X, it, converged, message


def bundle_adjust(detections: Tensor, rig: CameraRig, groups: Sequence[str] = DEFAULT_GROUPS,
                  frames: range | tuple[int, int] | None = None,
                  priors: RigPriors | dict | None = None, loss: RobustLoss | dict | None = None,
                  gauge: str | int = "mean", time_gauge: str | int = "mean",
                  max_time_offset: float = 5.0, fps: float | None = None,
                  trajectory_acceleration: float | None = 50.0, noise_px: float | None = None,
                  max_iterations: int = 200, tolerance: float = 1e-8,
                  min_detections: int = 20) -> BundleAdjustmentResult:
    """Refine a rig (and per-camera time offsets) from the subject's 2D detections.

    Args:
        detections: ``(T, C, K, 3)`` (u, v, confidence) in the pixels of ``rig``'s images;
            confidence 0 = not detected. Must be finite.
        rig: the given calibration of the ``C ≥ 2`` cameras.
        groups: refined groups (:data:`~torchmocap.cameras.rig_parameters.RIG_GROUPS`).
        frames: the frames refined, ``(start, stop)`` or a range (default: all); the refined
            rig applies to every frame.
        priors: :class:`~torchmocap.cameras.RigPriors` or a mapping of its fields (default
            widths: 5°, 0.25 m, 5 % focal, 20 px, 0.05 distortion, 2 frames).
        loss: :class:`~torchmocap.cameras.RobustLoss` or a mapping (default: Cauchy, 20 px,
            confidence > 0.3, confidence-weighted).
        gauge, time_gauge: ``"mean"``, a reference camera index, or ``"none"``
            (:mod:`torchmocap.cameras.rig_gauge`).
        max_time_offset: bound on ``|δ_c|`` in frames (a step beyond it is refused); must be
            smaller than the refined frames less one.
        fps: the frame rate (needed with time offsets and a ``trajectory_acceleration``).
        trajectory_acceleration: with time offsets refined, a Gaussian prior on the 3D
            trajectories' accelerations (second differences × fps², std in m/s²; default 50,
            what a kick reaches). Per-frame points free of it follow the detections' jitter,
            and an offset would then be fitted to that jitter (its "velocity"), not to the
            subject's motion, with a confidence nothing supports. None: no prior (points free
            per frame). Unused without time offsets (the points are free per frame).
        noise_px: σ, the detections' noise in pixels; None = measured from the residuals
            (their median distance / 1.18, the Rayleigh median, corrected for the degrees of
            freedom the fit takes; at least 0.01 px): first at the DLT start, then at the
            solution, re-solving until it changes by less than 2 % (5 solves at most). The
            start's residuals hold the calibration's error too; a σ measured there alone
            would make the priors too strong.
        max_iterations: Levenberg–Marquardt iterations at most.
        tolerance: converged when an accepted step lowers the objective by less than this
            fraction.
        min_detections: used detections (of points seen by two cameras) each camera needs.

    Returns:
        :class:`BundleAdjustmentResult`.

    Raises:
        RefinementError: fewer than two cameras; detections of the wrong shape, non-finite
            or negative confidences; a frame range outside the sequence; an unknown group,
            gauge or setting; a time-offset bound or prior not smaller than the sequence; a
            camera with fewer than ``min_detections`` usable detections; fewer residuals
            than unknowns. Each names the argument.
    """
    if not isinstance(rig, CameraRig):
        raise RefinementError(f"rig: expected a CameraRig, got {type(rig).__name__}")
    C = rig.num_cameras
    if C < 2:
        raise RefinementError(f"rig: refining cameras from detections needs at least 2 "
                              f"cameras, got {C}")
    if not isinstance(detections, Tensor) or detections.dim() != 4 or \
            detections.shape[1] != C or detections.shape[-1] != 3:
        shape = tuple(detections.shape) if isinstance(detections, Tensor) else \
            type(detections).__name__
        raise RefinementError(f"detections: expected shape (T, {C}, K, 3) (u, v, confidence "
                              f"per frame, camera and keypoint), got {shape}")
    if not detections.is_floating_point():
        raise RefinementError(f"detections: expected floating-point values, got "
                              f"{detections.dtype}")
    if not bool(torch.isfinite(detections).all()):
        raise RefinementError("detections: contains NaN or inf; give a missed keypoint "
                              "confidence 0 (and any finite u, v)")
    if bool((detections[..., 2] < 0).any()):
        raise RefinementError("detections: confidences must be >= 0")
    span = check_frames(frames, detections.shape[0])
    T = len(span)
    check_gauge(gauge, C, "gauge")
    check_gauge(time_gauge, C, "time_gauge")
    priors = RigPriors.from_dict(priors)
    loss = RobustLoss.from_dict(loss)
    max_iterations = int(_number(max_iterations, "max_iterations", "an iteration count >= 1",
                                 lambda v: v >= 1 and v == int(v)))
    tolerance = _number(tolerance, "tolerance", "a fraction in (0, 1)", lambda v: 0 < v < 1)
    min_detections = int(_number(min_detections, "min_detections", "a count >= 1",
                                 lambda v: v >= 1 and v == int(v)))
    if noise_px is not None:
        _number(noise_px, "noise_px", "a number of pixels > 0 (or None)", lambda v: v > 0)
    dev = detections.device
    par = RigParametrization(_copy_rig(rig, dev), groups, gauge, time_gauge)
    temporal = par.refines_time
    if temporal:
        _number(max_time_offset, "max_time_offset", "a bound in frames > 0", lambda v: v > 0)
        if T < 4:
            raise RefinementError(f"frames: refining time offsets needs at least 4 frames, got "
                                  f"{T}")
        if max_time_offset >= T - 1:
            raise RefinementError(f"max_time_offset: a bound of {max_time_offset:g} frames is "
                                  f"not smaller than the {T} refined frames less one")
        priors.check_time(T)
        if trajectory_acceleration is not None:
            _number(trajectory_acceleration, "trajectory_acceleration",
                    "an acceleration std in m/s^2 > 0 (or None)", lambda v: v > 0)
            if fps is None:
                raise RefinementError(
                    "fps: refining time offsets puts a prior on the trajectories' "
                    "accelerations (trajectory_acceleration, m/s^2), which needs the frame "
                    "rate; pass fps (or trajectory_acceleration=None)")
            _number(fps, "fps", "a frame rate > 0", lambda v: v > 0)

    det = detections[span.start:span.stop].to(torch.float64)
    uv, conf = det[..., :2], det[..., 2]
    weight = loss.detection_weights(conf)
    base = par.refined_rig(torch.zeros(C, NUM_VALUES, dtype=torch.float64, device=dev),
                           torch.float64)
    X0 = triangulate_dlt(uv, weight, base)  # (T, K, 3), NaN with < 2 views
    valid = torch.isfinite(X0).all(-1)
    if temporal:
        X0, keep = _fill_in_time(X0.nan_to_num(), valid)
        point_ok = keep.expand(T, -1)
    else:
        X0 = torch.where(valid[..., None], X0, torch.zeros_like(X0))
        point_ok = valid
    weight = weight * point_ok[:, None, :]
    used = weight > 0
    per_camera = used.sum((0, 2)).tolist()
    for c, n in enumerate(per_camera):
        if n < min_detections:
            raise RefinementError(
                f"detections: camera {rig.names[c]!r} has {n} usable detections in frames "
                f"{span.start}..{span.stop - 1} (confidence > {loss.min_confidence:g}, of "
                f"points seen by two cameras); at least min_detections = {min_detections} "
                "are needed")
    n_points = int(point_ok.sum()) if not temporal else int(point_ok[0].sum()) * T
    unknowns = par.num_parameters + 3 * n_points
    if 2 * int(used.sum()) <= unknowns:
        raise RefinementError(f"detections: {int(used.sum())} usable detections give "
                              f"{2 * int(used.sum())} residuals, not more than the "
                              f"{unknowns} unknowns (cameras and 3D points)")

    widths = priors.widths(par)
    smoothing = 0.0
    if temporal and trajectory_acceleration is not None:
        smoothing = (float(fps) ** 2 / float(trajectory_acceleration)) ** 2
    prob = _Problem(par, uv, weight, loss, widths, temporal, smoothing)
    y = torch.zeros(par.num_parameters, dtype=torch.float64, device=dev)
    X = X0.clone()
    r_before = prob.residuals(y, X)
    dof = math.sqrt(2 * int(used.sum()) / (2 * int(used.sum()) - unknowns))
    sigma = float(noise_px) if noise_px is not None else _sigma(r_before, used)
    iterations, rounds = 0, 0
    while True:
        rounds += 1
        y, X, it, converged, message = _levenberg_marquardt(
            prob, y, X, sigma, max_iterations - iterations, tolerance,
            max_time_offset if temporal else None)
        iterations += it
        if noise_px is not None or iterations >= max_iterations:
            break
        # the noise as the solution shows it (the start's residuals hold the calibration's
        # error too): re-solve until it settles
        new_sigma = _sigma(prob.residuals(y, X), used) * dof
        if abs(new_sigma - sigma) <= NOISE_TOLERANCE * sigma or rounds >= MAX_NOISE_ROUNDS:
            sigma = new_sigma
            break
        sigma = new_sigma
    cost0 = prob.cost(torch.zeros_like(y), X0, r_before, sigma)
    cost = prob.cost(y, X, prob.residuals(y, X), sigma)

    # uncertainty at the solution: IRLS weights, residuals whitened by the measured noise
    r, J_y, J_X, taps = prob.linearise(y, X)
    H_yy, g_y, H_pp, H_py, g_p = prob.normal_equations(y, X, r, J_y, J_X, taps, sigma)
    S, _, _, _ = _reduced_system(H_yy, g_y, H_pp, H_py, g_p, 0.0)
    L, info = torch.linalg.cholesky_ex(S)
    cov_y = torch.cholesky_inverse(L) if int(info) == 0 else torch.linalg.pinv(S)
    cov_z = par.basis @ cov_y @ par.basis.T
    cov = par.selection @ cov_z @ par.selection.T  # (C*13, C*13)
    refined = (par.selection.abs().sum(1) > 0).reshape(C, NUM_VALUES)
    std = torch.where(refined, cov.diagonal().clamp_min(0).sqrt().reshape(C, NUM_VALUES),
                      torch.full((C, NUM_VALUES), math.nan, dtype=torch.float64, device=dev))
    prior_width = torch.tensor(priors.value_widths(), dtype=torch.float64,
                               device=dev).expand(C, NUM_VALUES)
    prior_width = torch.where(refined, prior_width, torch.full_like(prior_width, math.nan))
    values = par.values(y)
    points = torch.where(point_ok[..., None], X, torch.full_like(X, math.nan))
    init = torch.where(point_ok[..., None], X0, torch.full_like(X0, math.nan))
    settings = {
        "groups": list(par.groups), "frames": [span.start, span.stop],
        "priors": priors.to_dict(), "loss": loss.to_dict(), "gauge": gauge,
        "time_gauge": time_gauge, "max_time_offset": float(max_time_offset) if temporal
        else None, "fps": fps, "trajectory_acceleration": trajectory_acceleration if temporal
        else None, "noise_px": noise_px, "max_iterations": max_iterations,
        "tolerance": tolerance, "min_detections": min_detections,
    }
    return BundleAdjustmentResult(
        rig=par.refined_rig(values, rig.K.dtype), values=values,
        time_offsets=values[:, 12].clone(), points=points, initial_points=init, frames=span,
        parametrization=par, covariance=cov, std=std, prior_width=prior_width,
        residual_px_before=_median_per_camera(r_before, used),
        residual_px_after=_median_per_camera(r, used), noise_px=sigma,
        noise_rounds=rounds, iterations=iterations, cost_initial=cost0, cost_final=cost,
        converged=converged, message=message, num_detections=int(used.sum()),
        detections_per_camera=[int(n) for n in per_camera], settings=settings)
