"""The model-based self-calibration: a rig refined jointly with a skeleton's poses.

Where :func:`~torchmocap.cameras.bundle_adjust` frees a 3D point per frame and keypoint, here
the points are the **skeleton's mapped keypoints** ``x_k(θ_t)``
(:func:`~torchmocap.skeleton.keypoint_positions`): the subject's bone lengths and the keypoint
map's offsets are constant over the frames, and only the poses ``θ_t (T, D)`` move. The
objective, minimised jointly over the poses and the rig's refined parameters ``y``
(:class:`~torchmocap.cameras.RigRefinement`: the same groups, gauge, priors and robust,
confidence-weighted reprojection loss as the bundle adjustment)::

    E(y, θ) = ½ Σ w ρ(‖π_y(x(θ_t)) − u‖²) / σ²  +  ½ Σ (z(y) / width)²
              + ½ Σ_t ‖(x_{t+1} − 2 x_t + x_{t−1}) fps² / a‖²

— reprojection, the rig's priors, and a Gaussian prior of std ``a`` (m/s²) on the keypoints'
accelerations (smooth motion). Per-camera time offsets are refined, when asked, by
interpolating the keypoint trajectories in time (Catmull–Rom,
:func:`~torchmocap.cameras.interpolate_in_time`).

Solved by L-BFGS (strong Wolfe line search) in float64. The reported standard deviations are
those of the rig's parameters **with the poses held at the solution** (the inverse Hessian of
``E`` in ``y`` alone): a lower bound on the uncertainty, since the poses could absorb part of a
change of the cameras.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchmocap.cameras import (
    BundleAdjustmentResult,
    CameraRig,
    RefinementError,
    RigPriors,
    RigRefinement,
    RobustLoss,
    reprojection_residuals,
)
from torchmocap.cameras.bundle_adjustment import _median_per_camera
from torchmocap.skeleton import KeypointMap, Skeleton, keypoint_positions

__all__ = ["fit_rig_to_skeleton"]


def fit_rig_to_skeleton(detections: Tensor, rig: CameraRig, skeleton: Skeleton,
                        keypoint_map: KeypointMap, theta: Tensor,
                        keypoint_names: Sequence[str],
                        groups: Sequence[str] = ("rotation", "translation"),
                        priors: RigPriors | dict | None = None,
                        loss: RobustLoss | dict | None = None, noise_px: float = 5.0,
                        fps: float = 30.0, trajectory_acceleration: float = 50.0,
                        iterations: int = 200, gauge: str | int = "mean",
                        start_values: Tensor | None = None, progress: bool = False
                        ) -> tuple[BundleAdjustmentResult, Tensor]:
    """Refine ``rig`` and the poses ``theta`` of ``skeleton`` to 2D detections.

    Args:
        detections: ``(T, C, K, 3)`` (u, v, confidence) in ``rig``'s pixels, columns named by
            ``keypoint_names``; confidence 0 = not detected.
        rig: the starting calibration of the ``C ≥ 2`` cameras.
        skeleton: the subject's skeleton (its rest offsets are held).
        keypoint_map: a :class:`~torchmocap.skeleton.KeypointMap` bound to ``skeleton``.
        theta: ``(T, D)`` starting poses (e.g. a keypoint subject fit's).
        keypoint_names: the ``K`` detection columns' names.
        groups: refined groups (:data:`~torchmocap.cameras.RIG_GROUPS`).
        priors, loss: as in :func:`~torchmocap.cameras.bundle_adjust`.
        noise_px: ``σ`` of the detections (px), e.g. the bundle adjustment's measured noise.
        fps: frame rate (the acceleration prior's time unit).
        trajectory_acceleration: ``a``, std of the keypoints' accelerations (m/s²).
        iterations: L-BFGS iterations at most.
        gauge: as in :func:`~torchmocap.cameras.bundle_adjust`.
        start_values: ``(C, 13)`` refined values to start from (e.g. a bundle adjustment's
            ``values`` with the same groups and gauge); None: the given calibration. The priors
            stay centred on ``rig``.
        progress: show a progress bar (tqdm) over the iterations.

    Returns:
        ``(result, theta)``: a :class:`~torchmocap.cameras.BundleAdjustmentResult` whose
        ``points`` are the skeleton's keypoints at the solution (``(T, K, 3)``, NaN for a
        column the map does not place) and ``initial_points`` those of the starting poses,
        and the fitted poses ``(T, D)`` float64.

    Raises:
        RefinementError: shapes that do not agree, fewer than two cameras, fewer than 4
            frames with time offsets, a setting out of range (named).
    """
    from tqdm.auto import tqdm

    if not isinstance(rig, CameraRig) or rig.num_cameras < 2:
        raise RefinementError("rig: expected a CameraRig of at least 2 cameras")
    C = rig.num_cameras
    if not isinstance(detections, Tensor) or detections.dim() != 4 or \
            detections.shape[1] != C or detections.shape[-1] != 3:
        raise RefinementError(f"detections: expected shape (T, {C}, K, 3), got "
                              f"{tuple(getattr(detections, 'shape', ()))}")
    T = detections.shape[0]
    if len(keypoint_names) != detections.shape[2]:
        raise RefinementError(f"keypoint_names: {len(keypoint_names)} names for "
                              f"{detections.shape[2]} detection columns")
    if not isinstance(theta, Tensor) or theta.shape != (T, skeleton.num_dofs):
        raise RefinementError(f"theta: expected shape ({T}, {skeleton.num_dofs}), got "
                              f"{tuple(getattr(theta, 'shape', ()))}")
    for name, v in (("noise_px", noise_px), ("fps", fps),
                    ("trajectory_acceleration", trajectory_acceleration)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or v <= 0:
            raise RefinementError(f"{name}: expected a number > 0, got {v!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise RefinementError(f"iterations: expected an int >= 1, got {iterations!r}")
    cols = keypoint_map.columns(list(keypoint_names))
    det = detections[:, :, cols].double()
    module = RigRefinement(rig.double(), groups, RigPriors.from_dict(priors),
                           RobustLoss.from_dict(loss), gauge=gauge, noise_px=float(noise_px))
    par = module.parametrization
    if par.refines_time and T < 4:
        raise RefinementError(f"detections: refining time offsets needs at least 4 frames, got "
                              f"{T}")
    sk = skeleton.double()
    kmap = keypoint_map
    q = theta.detach().double().clone().requires_grad_(True)
    smooth = (float(fps) ** 2 / float(trajectory_acceleration))

    def points_of(q: Tensor) -> Tensor:
        kin = sk(q)
        return keypoint_positions(kin.positions, kin.rotations, kmap)  # (T, K', 3)

    def energy() -> Tensor:
        X = points_of(q)
        data_prior = module(X, det)
        acc = (X[2:] - 2 * X[1:-1] + X[:-2]) * smooth
        return data_prior + 0.5 * (acc * acc).sum()

    weight = module.loss.detection_weights(det[..., 2])
    used = weight > 0
    with torch.no_grad():
        K0, R0, t0, d0 = module.cameras()
        r0 = reprojection_residuals(points_of(q), det, K0, R0, t0, d0)
        cost0 = float(energy())
    if start_values is not None:
        M0 = module.value_map.reshape(C * 13, -1)
        if not isinstance(start_values, Tensor) or start_values.shape != (C, 13):
            raise RefinementError(f"start_values: expected shape ({C}, 13), got "
                                  f"{tuple(getattr(start_values, 'shape', ()))}")
        with torch.no_grad():
            module.y.copy_(torch.linalg.lstsq(M0, start_values.double().reshape(-1, 1))
                           .solution[:, 0])
    opt = torch.optim.LBFGS([module.y, q], lr=1.0, max_iter=20, history_size=20,
                            line_search_fn="strong_wolfe", tolerance_change=1e-12,
                            tolerance_grad=1e-9)

    def closure():
        opt.zero_grad()
        e = energy()
        e.backward()
        return e

    rounds = max(1, iterations // 20)
    last, converged, message = cost0, False, "iteration limit"
    bar = tqdm(range(rounds), desc="model-based calibration", disable=not progress,
               leave=False)
    steps = 0
    for _ in bar:
        opt.step(closure)
        steps += 20
        with torch.no_grad():
            e = float(energy())
        bar.set_postfix(energy=f"{e:.1f}")
        if not math.isfinite(e):
            raise RefinementError("the model-based calibration diverged (a non-finite "
                                  "energy); check the detections and the start")
        if last - e <= 1e-9 * max(abs(last), 1.0):
            converged, message = True, "relative decrease below 1e-9"
            last = e
            break
        last = e
    bar.close()

    # the rig's uncertainty with the poses held: the inverse Hessian of E in y
    y_hat = module.y.detach().clone()
    q_hat = q.detach()

    def e_y(y: Tensor) -> Tensor:
        saved = module.y
        try:
            del module.y
            module.y = y  # a plain tensor for the functional Hessian
            X = points_of(q_hat)
            data_prior = module(X, det)
            acc = (X[2:] - 2 * X[1:-1] + X[:-2]) * smooth
            return data_prior + 0.5 * (acc * acc).sum()
        finally:
            del module.y
            module.y = saved

    H = torch.autograd.functional.hessian(e_y, y_hat)
    H = 0.5 * (H + H.T)
    L, info = torch.linalg.cholesky_ex(H)
    cov_y = torch.cholesky_inverse(L) if int(info) == 0 else torch.linalg.pinv(H)
    M = module.value_map.reshape(C * 13, -1).to(cov_y)
    cov = M @ cov_y @ M.T
    refined = (M.abs().sum(1) > 0).reshape(C, 13)
    nan = torch.full((C, 13), math.nan, dtype=torch.float64)
    std = torch.where(refined, cov.diagonal().clamp_min(0).sqrt().reshape(C, 13), nan)
    prior_width = torch.tensor(module.priors.value_widths(), dtype=torch.float64).expand(C, 13)
    prior_width = torch.where(refined, prior_width, nan)
    with torch.no_grad():
        values = module.values().detach()
        K1, R1, t1, d1 = module.cameras()
        X1 = points_of(q_hat)
        offsets = values[:, 12] if par.refines_time else None
        r1 = reprojection_residuals(X1, det, K1, R1, t1, d1, offsets)
    K_all = detections.shape[2]
    points = torch.full((T, K_all, 3), math.nan, dtype=torch.float64)
    points[:, cols] = X1
    init = torch.full((T, K_all, 3), math.nan, dtype=torch.float64)
    with torch.no_grad():
        init[:, cols] = points_of(theta.detach().double())
    settings = {"objective": "model", "groups": list(par.groups), "frames": [0, T],
                "priors": module.priors.to_dict(), "loss": module.loss.to_dict(),
                "gauge": gauge, "fps": float(fps),
                "trajectory_acceleration": float(trajectory_acceleration),
                "noise_px": float(noise_px), "max_iterations": iterations,
                "uncertainty": "with the poses held (a lower bound)"}
    result = BundleAdjustmentResult(
        rig=par.refined_rig(values, rig.K.dtype), values=values,
        time_offsets=values[:, 12].clone(), points=points, initial_points=init,
        frames=range(T), parametrization=par, covariance=cov, std=std,
        prior_width=prior_width, residual_px_before=_median_per_camera(r0, used),
        residual_px_after=_median_per_camera(r1, used), noise_px=float(noise_px),
        noise_rounds=1, iterations=steps, cost_initial=cost0, cost_final=last,
        converged=converged, message=message, num_detections=int(used.sum()),
        detections_per_camera=[int(n) for n in used.sum((0, 2)).tolist()], settings=settings)
    return result, q_hat
