"""Offline smoothing of any track: a constant-velocity Kalman smoother per DoF, noise by ML.

A particle tracker's per-frame estimates jitter about the motion: each frame's estimate carries
that frame's sampling noise and sensor noise, independently of the next. Once the whole clip is
tracked, every DoF's estimates ``y_t`` can be read as noisy observations of a smooth trajectory:
the state ``s_t = (x_t, v_t)`` (value and velocity per frame) follows the constant-velocity model
with white-noise acceleration (spectral density ``q`` per frame³),

    s_t = F s_{t-1} + w_t,   F = [[1, 1], [0, 1]],   w_t ~ N(0, q [[1/3, 1/2], [1/2, 1]]),
    y_t = x_t + e_t,         e_t ~ N(0, r),

and the Rauch–Tung–Striebel smoother returns ``E[x_t | y_0..y_{T-1}]`` — the exact posterior mean
of that linear-Gaussian model (equivalently the minimiser of the quadratic trajectory energy).
Frame 0 is the known initial pose (kept exactly); the velocity starts diffuse.

The two variances are not tuned: by default both are estimated by **maximum likelihood** (the
prediction-error decomposition of the Kalman filter's innovations, frames 2..T-1, on a
log-spaced grid), one pair shared by the 3-axis joints' rotations, one by the other rotation
DoFs and one by the root translation. A track
that is already smooth gets a small ``r`` and is left almost as it is (the true motion of six
real clips, smoothed so, moves their joints by 0–1.5 mm); a jittery one gets a larger ``r`` relative
to ``q`` and is smoothed more. ``per_dof=True`` fits a pair per DoF instead (fewer frames per
estimate; on tracker output it follows the error bursts of single DoFs and smooths less), and
either variance can be fixed by config.

The rotation of every 3-axis joint (root, spine, shoulders, hips of human31) is smoothed on
SO(3), not as its three Euler angles: a particle tracker's estimate may jump between the two
Euler branches of the same rotation (``(a, b, c)`` and about ``(a + π, π - b, c + π)``), which
is no motion at all but, read as angles, a 180° excursion that the smoother would average into
other rotations. Each such joint's rotations become quaternions with a continuous sign, the four
components are smoothed (one noise pair for all of them), renormalised and turned back into the
joint's angles on the branch nearest the tracker's estimate of that frame
(:func:`~torchmocap.filters.angles_from_matrix`). The other rotation DoFs (hinges, 2-axis
joints) are unwrapped over time (a heading crossing ±π is not a 2π jump) and smoothed as angles;
``rotations="angles"`` smooths every rotation DoF so. DoFs without limits are wrapped back to
``(-π, π]``; DoFs with limits are clamped into them (the smoother's weights can overshoot at a
limit) and the clamped values are counted.

``lag=L`` makes it a fixed-lag smoother: frame ``t`` sees the estimates up to ``t + L`` only.

The smoother sees the future: compare it with other smoothers, not with filters (the tracker's
``Track.filtered`` keeps the filtered estimates, ``metrics.json`` reports them under
``filtered``). Functional core: :func:`cv_kalman_smoother`, :func:`fit_cv_noise`; module:
:class:`KalmanSmoother` (``+smoother@tracker.smoother=kalman``).
"""

from __future__ import annotations

import dataclasses
import math

import torch

from torchmocap.filters.optim.rotations import skeleton_rotation_groups
from torchmocap.filters.smoothing.base import Smoother
from torchmocap.geometry import wrap_angle
from torchmocap.geometry.quaternions import matrix_to_quaternion, quaternion_to_matrix

__all__ = ["KalmanSmoother", "cv_kalman_smoother", "fit_cv_noise", "unwrap_angles"]

ROTATIONS = ("so3", "angles")

#: variance of the diffuse initial velocity (per frame², in the DoF's unit²)
_DIFFUSE = 1e8


def unwrap_angles(theta: torch.Tensor) -> torch.Tensor:
    """``theta (T, ...)`` with every step's change wrapped to ``(-π, π]`` and re-accumulated:
    a continuous angle sequence equal to the input modulo 2π (frame 0 unchanged)."""
    if theta.shape[0] < 2:
        return theta.clone()
    d = torch.diff(theta, dim=0)
    d = wrap_angle(d)
    return torch.cat([theta[:1], theta[:1] + torch.cumsum(d, 0)])


def _forward(y: torch.Tensor, r: torch.Tensor, q: torch.Tensor, keep: bool = True):
    """Kalman filter of the constant-velocity model, batched over ``y (T, ...)``'s trailing
    dimensions (``r``, ``q`` broadcast against them). Returns the filtered and predicted
    moments (lists over t; ``None`` with ``keep=False``, which needs memory for one step only:
    the likelihood grid of a long clip) and the log-likelihood of the innovations of frames
    2..T-1."""
    T = y.shape[0]
    shape = torch.broadcast_shapes(y.shape[1:], r.shape, q.shape)
    y = y.expand(T, *shape)
    zero = torch.zeros(shape, dtype=y.dtype, device=y.device)
    # frame 0 known exactly; the velocity diffuse
    m0, m1 = y[0].clone(), zero.clone()
    p00, p01, p11 = zero.clone(), zero.clone(), zero + _DIFFUSE
    filt = [(m0, m1, p00, p01, p11)] if keep else None
    pred = [None] if keep else None
    loglik = zero.clone()
    for t in range(1, T):
        a0, a1 = m0 + m1, m1
        b00 = p00 + 2 * p01 + p11 + q / 3
        b01 = p01 + p11 + q / 2
        b11 = p11 + q
        if keep:
            pred.append((a0, a1, b00, b01, b11))
        s = b00 + r
        e = y[t] - a0
        k0, k1 = b00 / s, b01 / s
        m0, m1 = a0 + k0 * e, a1 + k1 * e
        p00, p01, p11 = b00 - k0 * b00, b01 - k0 * b01, b11 - k1 * b01
        if t >= 2:  # the first innovation only resolves the diffuse velocity
            loglik = loglik - 0.5 * (torch.log(2 * math.pi * s) + e * e / s)
        if keep:
            filt.append((m0, m1, p00, p01, p11))
    return filt, pred, loglik


def _rts_step(f, p, xs, vs):
    """One Rauch–Tung–Striebel step: the smoothed ``(x, v)`` at ``t`` from those at ``t + 1``,
    the filtered moments ``f`` at ``t`` and the predicted moments ``p`` at ``t + 1``."""
    m0, m1, p00, p01, p11 = f
    a0, a1, b00, b01, b11 = p
    # C = P_t F^T (P'_{t+1})^-1; P_t F^T = [[p00 + p01, p01], [p01 + p11, p11]]
    det = b00 * b11 - b01 * b01
    i00, i01, i11 = b11 / det, -b01 / det, b00 / det
    u00, u01, u10, u11 = p00 + p01, p01, p01 + p11, p11
    c00, c01 = u00 * i00 + u01 * i01, u00 * i01 + u01 * i11
    c10, c11 = u10 * i00 + u11 * i01, u10 * i01 + u11 * i11
    d0, d1 = xs - a0, vs - a1
    return m0 + c00 * d0 + c01 * d1, m1 + c10 * d0 + c11 * d1


def _check_lag(lag) -> int | None:
    if lag is None:
        return None
    if isinstance(lag, bool) or not isinstance(lag, int) or lag < 0:
        raise ValueError(f"lag: expected an int >= 0 (frames) or None (the whole clip), "
                         f"got {lag!r}")
    return lag


def cv_kalman_smoother(y: torch.Tensor, r, q, lag: int | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Rauch–Tung–Striebel smoother of the constant-velocity model for every column of ``y``.

    Args:
        y: ``(T, ...)`` observations (frame 0 is taken as exact).
        r: observation variance, broadcastable to ``y.shape[1:]`` (> 0).
        q: white-noise acceleration spectral density per frame³, broadcastable likewise (> 0).
        lag: ``None`` (default): fixed-interval smoothing, every frame from the whole series;
            ``L >= 0``: fixed-lag smoothing, frame ``t`` from ``y[0 .. t + L]`` only (what an
            online tracker delayed by ``L`` frames can report; ``0`` is the Kalman filter).

    Returns:
        ``(x (T, ...), loglik (...))``: the smoothed values and the log-likelihood of the
        innovations of frames 2..T-1 (the diffuse velocity takes frame 1).
    """
    if y.dim() < 1 or y.shape[0] < 1 or not bool(torch.isfinite(y).all()):
        raise ValueError(f"y: expected finite observations (T >= 1, ...), got shape "
                         f"{tuple(y.shape)}")
    lag = _check_lag(lag)
    r = torch.as_tensor(r, dtype=y.dtype, device=y.device)
    q = torch.as_tensor(q, dtype=y.dtype, device=y.device)
    if not bool((r > 0).all()) or not bool((q > 0).all()):
        raise ValueError("r, q: expected variances > 0")
    filt, pred, loglik = _forward(y, r, q)
    T = y.shape[0]
    if lag is not None and lag < T - 1:
        return _fixed_lag(filt, pred, lag), loglik
    xs, vs = filt[-1][0], filt[-1][1]
    out = [xs]
    for t in range(T - 2, -1, -1):
        xs, vs = _rts_step(filt[t], pred[t + 1], xs, vs)
        out.append(xs)
    return torch.stack(out[::-1]), loglik


def _fixed_lag(filt, pred, lag: int) -> torch.Tensor:
    """Fixed-lag smoothed values ``(T, ...)``: for every frame ``t`` at once, the RTS pass from
    the filtered state at ``e = min(t + lag, T - 1)`` back to ``t`` (``lag`` vectorised steps)."""
    T = len(filt)
    f_all = [torch.stack([f[i] for f in filt]) for i in range(5)]  # (T, ...) each
    p_all = [torch.stack([pred[max(t, 1)][i] for t in range(T)]) for i in range(5)]
    t_idx = torch.arange(T, device=f_all[0].device)
    end = (t_idx + lag).clamp(max=T - 1)
    xs, vs = f_all[0][end], f_all[1][end]
    shape = (T,) + (1,) * (xs.dim() - 1)
    for k in range(1, lag + 1):
        j = end - k  # the step each frame's pass is at (<= T - 2); done once j < t
        active = (j >= t_idx).view(shape)
        jj = j.clamp(min=0)
        nx, nv = _rts_step([a[jj] for a in f_all], [a[jj + 1] for a in p_all], xs, vs)
        xs, vs = torch.where(active, nx, xs), torch.where(active, nv, vs)
    return xs


def fit_cv_noise(y: torch.Tensor, r_grid: torch.Tensor, q_grid: torch.Tensor,
                 shared: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Maximum-likelihood ``(r, q)`` of every column of ``y (T, N)`` over a grid.

    Args:
        y: ``(T, N)`` observations, ``T >= 3``.
        r_grid, q_grid: ``(Gr,)``, ``(Gq,)`` candidate variances (> 0); pass one value to fix one.
        shared: one ``(r, q)`` for all columns (maximising their summed log-likelihood) instead
            of one per column.

    Returns:
        ``(r (N,), q (N,), loglik (N,))`` at the grid maximum.
    """
    if y.dim() != 2 or y.shape[0] < 3:
        raise ValueError(f"y: expected (T >= 3, N), got {tuple(y.shape)}")
    rr, qq = torch.meshgrid(r_grid.to(y), q_grid.to(y), indexing="ij")
    rr, qq = rr.reshape(-1, 1), qq.reshape(-1, 1)  # (G, 1) against the columns
    _, _, ll = _forward(y[:, None, :], rr, qq, keep=False)  # (G, N)
    best = ll.sum(1).argmax().expand(y.shape[1]) if shared else ll.argmax(0)
    cols = torch.arange(y.shape[1], device=y.device)
    return rr[best, 0], qq[best, 0], ll[best, cols]


def _grid(lo: float, hi: float, n: int, fixed) -> torch.Tensor:
    if fixed is not None:
        return torch.tensor([float(fixed) ** 2], dtype=torch.float64)
    return torch.logspace(math.log10(lo ** 2), math.log10(hi ** 2), n, dtype=torch.float64)


def _std_or_none(name: str, v):
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name}: expected a finite number > 0 or null (estimated), got {v!r}")
    return float(v)


class KalmanSmoother(Smoother):
    """Constant-velocity Rauch–Tung–Striebel smoother of every DoF of a track (any inference).

    Args:
        skeleton: the tracking model: its 3-axis joints are smoothed on SO(3), its translation
            DoFs use the translation settings, its rotation DoFs are kept in their limits, its
            DoF names label the report.
        measurement_std_deg, acceleration_std_deg: per-frame std of the estimates' noise
            (degrees) and the white-noise acceleration's std (degrees per frame², i.e.
            ``sqrt(q)``) of the rotation DoFs; ``None`` (default): estimated by maximum
            likelihood.
        translation_measurement_std, translation_acceleration_std: the same for the root
            translation (metres); ``None``: estimated.
        grid_size: points of each log-spaced likelihood grid (``1e-4``–``50`` degrees,
            ``1e-5``–``0.5`` m).
        clamp_limits: clamp the smoothed rotation DoFs into the skeleton's limits.
        per_dof: estimate the variances per DoF (quaternion component) instead of one pair per
            group (3-axis joints, other rotation DoFs, root translation).
        rotations: ``"so3"`` (default): 3-axis joints smoothed as rotations (quaternions), the
            other rotation DoFs as angles; ``"angles"``: every rotation DoF as an angle. Without
            a skeleton every DoF is an angle.
        lag: ``None`` (default): every frame smoothed from the whole clip; ``L >= 0`` frames:
            frame ``t`` from the estimates up to ``t + L`` only (fixed-lag: what a tracker
            reporting ``L`` frames late could give; ``0`` = the Kalman filter of the
            estimates). The noise is still estimated from the whole track.

    ``smooth(track)`` returns the track with ``theta`` smoothed and ``filtered`` the tracker's
    estimates; its ``smoother`` report gives the fitted stds per DoF (``dofs``), their
    medians, the log-likelihood and the number of clamped values.
    """

    ROTATION_RANGE_DEG = (1e-4, 50.0)
    TRANSLATION_RANGE_M = (1e-5, 0.5)

    def __init__(self, skeleton=None, measurement_std_deg: float | None = None,
                 acceleration_std_deg: float | None = None,
                 translation_measurement_std: float | None = None,
                 translation_acceleration_std: float | None = None,
                 grid_size: int = 33, clamp_limits: bool = True, per_dof: bool = False,
                 rotations: str = "so3", lag: int | None = None) -> None:
        super().__init__()
        self.measurement_std_deg = _std_or_none("measurement_std_deg", measurement_std_deg)
        self.acceleration_std_deg = _std_or_none("acceleration_std_deg", acceleration_std_deg)
        self.translation_measurement_std = _std_or_none("translation_measurement_std",
                                                        translation_measurement_std)
        self.translation_acceleration_std = _std_or_none("translation_acceleration_std",
                                                         translation_acceleration_std)
        if isinstance(grid_size, bool) or not isinstance(grid_size, int) or grid_size < 2:
            raise ValueError(f"grid_size: expected an int >= 2, got {grid_size!r}")
        for name, v in (("clamp_limits", clamp_limits), ("per_dof", per_dof)):
            if not isinstance(v, bool):
                raise ValueError(f"{name}: expected a bool, got {v!r}")
        self.grid_size, self.clamp_limits, self.per_dof = grid_size, clamp_limits, per_dof
        if rotations not in ROTATIONS:
            raise ValueError(f"rotations: expected one of {ROTATIONS}, got {rotations!r}")
        self.rotations = rotations
        self.lag = _check_lag(lag)
        # what is read of the skeleton (not the module itself: the tracker owns it)
        self.ball_groups = [] if skeleton is None else skeleton_rotation_groups(
            skeleton, [n for n, a in zip(skeleton.joint_names, skeleton.joint_axes)
                       if len(a) == 3])
        self.has_skeleton = skeleton is not None
        self.num_dofs = None if skeleton is None else int(skeleton.num_dofs)
        self.translation_dofs = [] if skeleton is None else list(skeleton.translation_dofs)
        self.dof_names = None if skeleton is None else list(skeleton.dof_names)
        if skeleton is not None:
            self.register_buffer("lower", skeleton.lower.detach().clone(), persistent=False)
            self.register_buffer("upper", skeleton.upper.detach().clone(), persistent=False)

    def _series(self, y: torch.Tensor, D: int):
        """The smoothed groups: ``(kind, dof indices, observations (T, N))`` — the 3-axis
        joints' rotations as sign-continuous quaternions (``so3``), the other rotation DoFs as
        unwrapped angles, the root translation."""
        trans = set(self.translation_dofs)
        ball = list(self.ball_groups) if self.rotations == "so3" else []
        in_ball = {i for g in ball for i in g.indices}
        angles = [d for d in range(D) if d not in trans and d not in in_ball]
        out = []
        if ball:
            qs = []
            for g in ball:
                q = matrix_to_quaternion(g.matrix(y[:, list(g.indices)]))  # (T, 4)
                sign = torch.sign((q[1:] * q[:-1]).sum(-1))
                sign = torch.cat([sign.new_ones(1), torch.cumprod(
                    torch.where(sign == 0, torch.ones_like(sign), sign), 0)])
                qs.append(q * sign[:, None])
            out.append(("so3", [i for g in ball for i in g.indices], torch.cat(qs, 1)))
        if angles:
            out.append(("rotation", angles, unwrap_angles(y[:, angles])))
        if trans:
            idx = sorted(trans)
            out.append(("translation", idx, y[:, idx]))
        return ball, out

    def _grids(self, kind: str):
        if kind == "translation":
            lo, hi = self.TRANSLATION_RANGE_M
            fr, fq = self.translation_measurement_std, self.translation_acceleration_std
        else:  # degrees -> radians (quaternion components: half the angle)
            f = math.pi / 180.0 * (0.5 if kind == "so3" else 1.0)
            lo, hi = (v * f for v in self.ROTATION_RANGE_DEG)
            fr = None if self.measurement_std_deg is None else self.measurement_std_deg * f
            fq = None if self.acceleration_std_deg is None else self.acceleration_std_deg * f
        return (_grid(lo, hi, self.grid_size, fr), _grid(lo, hi, self.grid_size, fq))

    def smooth_theta(self, theta: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """``theta (T, D)`` smoothed (float64 inside, returned in ``theta``'s dtype/device) and
        the report."""
        if theta.dim() != 2:
            raise ValueError(f"track.theta: expected (T, D), got {tuple(theta.shape)}")
        if not bool(torch.isfinite(theta).all()):
            raise ValueError("track.theta: expected finite values")
        if self.num_dofs is not None and theta.shape[1] != self.num_dofs:
            raise ValueError(f"track.theta: expected {self.num_dofs} DoFs (the skeleton's), "
                             f"got {theta.shape[1]}")
        T, D = theta.shape
        y = theta.detach().to("cpu", torch.float64)
        if T < 3:
            return theta.clone(), {"name": "kalman", "changed_frames": 0,
                                   "reason": f"{T} frames; the smoother needs 3"}
        out = y.clone()
        # per DoF: the fitted stds in degrees (rotations) or millimetres (translation)
        r_all = torch.zeros(D, dtype=torch.float64)
        q_all = torch.zeros(D, dtype=torch.float64)
        loglik = 0.0
        ball, series = self._series(y, D)
        moved = torch.zeros(D, dtype=torch.bool)  # DoFs the tracker moved (and so smoothed)
        for kind, idx, yg in series:
            # a DoF the tracker never moved (an upper-body preset's legs) says nothing about the
            # noise: it is left as it is and kept out of the fit
            active = (yg != yg[:1]).any(0)
            r = torch.zeros(yg.shape[1], dtype=torch.float64)
            q = torch.zeros(yg.shape[1], dtype=torch.float64)
            xs = yg.clone()
            if bool(active.any()):
                ra, qa, ll = fit_cv_noise(yg[:, active], *self._grids(kind),
                                          shared=not self.per_dof)
                xs[:, active] = cv_kalman_smoother(yg[:, active], ra, qa, lag=self.lag)[0]
                r[active], q[active] = ra, qa
                loglik += float(ll.sum())
            if kind == "so3":
                xs = torch.nn.functional.normalize(xs.reshape(T, len(ball), 4), dim=-1)
                scale = 2 * 180.0 / math.pi  # quaternion component -> rotation angle
                for k, g in enumerate(ball):
                    gi = list(g.indices)
                    if not bool(active[4 * k:4 * k + 4].any()):
                        continue  # a joint held still: its angles stay exactly as they were
                    moved[gi] = True
                    R = quaternion_to_matrix(xs[:, k])
                    out[:, gi] = g.values(R, y[:, gi])  # the branch nearest the estimate
                    r_all[gi] = float(r[4 * k:4 * k + 4].mean().sqrt()) * scale
                    q_all[gi] = float(q[4 * k:4 * k + 4].mean().sqrt()) * scale
            else:
                out[:, idx] = xs
                moved[torch.tensor(idx)[active]] = True
                scale = 1000.0 if kind == "translation" else 180.0 / math.pi
                r_all[idx], q_all[idx] = r.sqrt() * scale, q.sqrt() * scale
        trans = set(self.translation_dofs)
        rot = [d for d in range(D) if d not in trans]
        rot_moved = [d for d in rot if bool(moved[d])]
        clamped = 0
        if self.has_skeleton:
            lo_l = self.lower.to("cpu", torch.float64)
            hi_l = self.upper.to("cpu", torch.float64)
            free = torch.zeros(D, dtype=torch.bool)
            free[rot] = ~(torch.isfinite(lo_l[rot]) & torch.isfinite(hi_l[rot]))
            wrapped = wrap_angle(out)
            out = torch.where(free, wrapped, out)
            if self.clamp_limits:
                c = torch.maximum(torch.minimum(out, hi_l), lo_l)
                clamped = int((c != out).sum())
                out = c
        else:
            out = wrap_angle(out)
        out[0] = y[0]
        names = self.dof_names or [str(d) for d in range(D)]
        result = out.to(theta.dtype).to(theta.device)
        change = wrap_angle(out[:, rot] - y[:, rot])
        info = {
            "name": "kalman",
            "rotations": self.rotations if ball or self.rotations == "angles" else "angles",
            "changed_frames": int((result != theta).any(-1).sum()),
            "mean_change_deg": round(float(torch.rad2deg(change.abs().mean())), 4)
            if rot else 0.0,
            "measurement_std_deg_median": round(float(r_all[rot_moved].median()), 4)
            if rot_moved else None,
            "acceleration_std_deg_median": round(float(q_all[rot_moved].median()), 4)
            if rot_moved else None,
            "log_likelihood": round(loglik, 3),
            "lag": self.lag,
            "clamped": clamped,
            "held_dofs": int((~moved).sum()),
            "dofs": {names[d]: {"measurement_std": round(float(r_all[d]), 4),
                                "acceleration_std": round(float(q_all[d]), 4)}
                     for d in range(D)},
        }
        return result, info

    def smooth(self, track):
        theta, info = self.smooth_theta(track.theta)
        return dataclasses.replace(track, theta=theta, filtered=track.theta, smoother=info)

    def extra_repr(self) -> str:
        def s(v):
            return "ML" if v is None else f"{v:g}"
        return (f"measurement_std_deg={s(self.measurement_std_deg)}, "
                f"acceleration_std_deg={s(self.acceleration_std_deg)}, "
                f"translation=({s(self.translation_measurement_std)}, "
                f"{s(self.translation_acceleration_std)}), grid_size={self.grid_size}"
                f"{', per_dof=True' if self.per_dof else ''}"
                f"{'' if self.lag is None else f', lag={self.lag}'}")
