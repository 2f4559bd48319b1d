"""Robust 2D-joint reprojection energy (Sminchisescu & Triggs 2003, §2 and §5.1).

The observation of a frame is ``joints2d (C, J, 3)`` = (u, v, confidence) per camera and
skeleton joint (confidence 0 = missed / invisible). For a pose ``theta`` with joint centres
``X_j`` and pinhole projections ``pi_c(X_j)`` the energy is

    V(theta) = N * (sum_cj w_cj rho(z_cj)) / (sum_cj w_cj),   z_cj = |pi_c(X_j) - u_cj|^2 / s^2

with ``s`` the robust scale in pixels, ``w_cj`` the detection confidences (0 for a missed joint:
it is skipped), ``N`` the number of valid detections (``reduction="sum"``; ``"mean"`` drops the
factor ``N``) and ``rho`` one of

=================  ================================  ========================================
``cauchy``         ``log(1 + z)`` (Lorentzian)        influence redescends, cost grows as log
``geman_mcclure``  ``z / (1 + z)``                    bounded cost (< 1 per detection)
``huber``          ``z`` for ``z <= 1``, else         linear tails
                   ``2 sqrt(z) - 1``
``gaussian``       ``z``                              the paper's squared-distance
                                                      initialisation cost (§5.1); not robust
=================  ================================  ========================================

With equal confidences ``V = sum_cj rho(z_cj)``: a robust negative log-likelihood summed over the
detections, so its inverse Hessian at a mode is a covariance in pose units (what covariance-
scaled sampling needs). The confidences only redistribute the influence of the detections. A
Gaussian pixel noise of std ``sigma`` corresponds to ``s = sqrt(2) sigma`` near ``z = 0``.

A frame without any valid detection carries no evidence and must not score as a perfect match:
``on_empty="raise"`` (default) refuses it in :meth:`Joints2DLikelihood.prepare`;
``"uninformative"`` gives every pose the same energy ``n_slots * rho(1)`` (the cost of being one
robust scale off at every joint slot) and flags the observation (``Joints2DObservation.empty``).

Derivatives (:meth:`Joints2DLikelihood.gauss_newton`): the analytic gradient through the
skeleton's geometric Jacobian (:meth:`~torchmocap.skeleton.Skeleton.jacobian`) and the pinhole
projection's ``2 x 3`` Jacobian, and the Gauss–Newton (IRLS) Hessian
``H = sum w' J^T J`` with ``w' = (N / W) w rho'(z) 2 / s^2`` — positive semi-definite, equal to the
true Hessian wherever the residuals vanish. Cameras with lens distortion are supported by the
energy (autograd) but not by the analytic derivatives.

Shapes: ``P`` poses, ``D`` DoF, ``C`` cameras, ``J`` joints (``J'`` used ones).

Example:
    >>> from torchmocap.skeleton import human31
    >>> from torchmocap.cameras import make_ring_rig
    >>> from torchmocap.data import Frame
    >>> from torchmocap.likelihoods import FrameEnergy
    >>> sk, rig = human31(), make_ring_rig(1).float()
    >>> th = sk.zero_pose((1,))
    >>> pix = rig.project(sk(th).positions[0])[0][0]            # (J, 2)
    >>> frame = Frame(0, 0.0, joints2d=torch.cat([pix, torch.ones(21, 1)], -1)[None])
    >>> term = Joints2DLikelihood(rig, skeleton=sk)
    >>> V = FrameEnergy(term, term.prepare(frame), sk)
    >>> V(torch.cat([th, th + 0.1])).shape
    torch.Size([2])
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from torchmocap.likelihoods.base import Likelihood, Poses

__all__ = [
    "EmptyEvidenceError",
    "Joints2DLikelihood",
    "Joints2DObservation",
    "ROBUST_COSTS",
    "joints2d_energy",
    "robust_cost",
]

#: Names of the robust functions ``rho(z)`` (see the module docstring).
ROBUST_COSTS = ("cauchy", "geman_mcclure", "huber", "gaussian")
_DEPTH_EPS = 1e-6  # as torchmocap.cameras.projection (depth clamp of points behind a camera)


class EmptyEvidenceError(ValueError):
    """A frame has no valid 2D joint detection (every confidence is 0)."""


def robust_cost(z: torch.Tensor, kind: str = "cauchy") -> tuple[torch.Tensor, torch.Tensor]:
    """``rho(z)`` and ``d rho / d z`` of a squared normalised residual ``z >= 0``.

    Args:
        z: ``(*)`` squared residuals divided by the squared scale.
        kind: one of :data:`ROBUST_COSTS`.

    Returns:
        ``rho (*)`` and ``rho' (*)``.

    Example:
        >>> robust_cost(torch.tensor([0.0, 3.0]), "cauchy")[0]
        tensor([0.0000, 1.3863])
    """
    if kind == "cauchy":
        return torch.log1p(z), 1.0 / (1.0 + z)
    if kind == "geman_mcclure":
        return z / (1.0 + z), 1.0 / (1.0 + z) ** 2
    if kind == "huber":
        core = z <= 1.0
        sq = torch.where(core, torch.ones_like(z), z).sqrt()
        return (torch.where(core, z, 2.0 * sq - 1.0),
                torch.where(core, torch.ones_like(z), 1.0 / sq))
    if kind == "gaussian":
        return z, torch.ones_like(z)
    raise ValueError(f"robust: expected one of {ROBUST_COSTS}, got {kind!r}")


@dataclass
class Joints2DObservation:
    """A frame's 2D joints prepared for :func:`joints2d_energy`.

    Attributes:
        uv: ``(C, J', 2)`` detected pixels of the used joints.
        weight: ``(C, J')`` confidences (0 = skipped).
        joints: ``(J',)`` int64 indices of the used joints into the skeleton's joints.
        num_valid: number of detections with a positive weight ``N``.
        total_weight: ``W = sum weight``.
        empty: the frame has no valid detection (``on_empty="uninformative"``).
    """

    uv: torch.Tensor
    weight: torch.Tensor
    joints: torch.Tensor
    num_valid: int
    total_weight: float
    empty: bool = False


def _norm_factor(obs: Joints2DObservation, reduction: str) -> float:
    if obs.empty:
        return 0.0
    n = obs.num_valid if reduction == "sum" else 1
    return n / obs.total_weight


def _empty_energy(obs: Joints2DObservation, robust: str) -> float:
    slots = obs.weight.numel()
    return slots * float(robust_cost(torch.ones((), dtype=torch.float64), robust)[0])


def joints2d_energy(positions: torch.Tensor, observation: Joints2DObservation, rig,
                    scale_px: float = 4.0, robust: str = "cauchy",
                    reduction: str = "sum") -> torch.Tensor:
    """The robust 2D-joint energy of joint positions (module docstring).

    Args:
        positions: ``(P, J, 3)`` world joint centres (metres) of the skeleton's joints.
        observation: :class:`Joints2DObservation` (``Joints2DLikelihood.prepare``).
        rig: :class:`~torchmocap.cameras.CameraRig` with ``C`` cameras.
        scale_px: robust scale ``s`` in pixels.
        robust: one of :data:`ROBUST_COSTS`.
        reduction: ``"sum"`` or ``"mean"``.

    Returns:
        ``(P,)`` energies (differentiable in ``positions``).
    """
    P = positions.shape[0]
    if observation.empty:
        return positions.new_full((P,), _empty_energy(observation, robust)) \
            + 0.0 * positions.sum((-1, -2))
    X = positions.index_select(-2, observation.joints.to(positions.device))
    pix = rig.project(X)[0]  # (P, C, J', 2)
    r = pix - observation.uv.to(pix)
    z = (r * r).sum(-1) / (scale_px * scale_px)
    rho, _ = robust_cost(z, robust)
    w = observation.weight.to(pix)
    return (w * rho).sum((-1, -2)) * _norm_factor(observation, reduction)


class Joints2DLikelihood(Likelihood):
    """Robust reprojection energy of the skeleton's joints against 2D detections.

    Args:
        rig: the :class:`~torchmocap.cameras.CameraRig` of the detections (runtime dependency).
        skeleton: the tracking skeleton (runtime dependency; needed for ``joints`` by name and
            for :meth:`gauss_newton` without a :class:`Poses`).
        scale_px: robust scale ``s`` (pixels).
        robust: ``"cauchy"`` (default), ``"geman_mcclure"``, ``"huber"`` or ``"gaussian"``.
        joints: names of the joints to use (default: every joint of the skeleton).
        min_confidence: detections below this confidence are skipped.
        reduction: ``"sum"`` (``N`` times the weighted mean cost; default) or ``"mean"``.
        on_empty: ``"raise"`` (:class:`EmptyEvidenceError` from :meth:`prepare`) or
            ``"uninformative"`` (a constant, non-zero energy; the observation is flagged).
    """

    requires = ("joints2d",)

    def __init__(self, rig, skeleton=None, scale_px: float = 4.0, robust: str = "cauchy",
                 joints: Sequence[str] | None = None, min_confidence: float = 0.0,
                 reduction: str = "sum", on_empty: str = "raise") -> None:
        super().__init__()
        if rig is None:
            raise ValueError("rig: Joints2DLikelihood needs the camera rig of the detections")
        if not (isinstance(scale_px, (int, float)) and not isinstance(scale_px, bool)
                and math.isfinite(scale_px) and scale_px > 0):
            raise ValueError(f"scale_px: expected a finite number > 0, got {scale_px!r}")
        if robust not in ROBUST_COSTS:
            raise ValueError(f"robust: expected one of {ROBUST_COSTS}, got {robust!r}")
        if reduction not in ("sum", "mean"):
            raise ValueError(f"reduction: expected 'sum' or 'mean', got {reduction!r}")
        if on_empty not in ("raise", "uninformative"):
            raise ValueError(f"on_empty: expected 'raise' or 'uninformative', got {on_empty!r}")
        if not (isinstance(min_confidence, (int, float)) and 0 <= min_confidence <= 1):
            raise ValueError(f"min_confidence: expected a number in [0, 1], got "
                             f"{min_confidence!r}")
        self.rig = rig
        self.skeleton = skeleton
        self.scale_px = float(scale_px)
        self.robust = robust
        self.reduction = reduction
        self.on_empty = on_empty
        self.min_confidence = float(min_confidence)
        self.joint_names = None if joints is None else [str(j) for j in joints]
        if self.joint_names is not None:
            if skeleton is None:
                raise ValueError("joints: selecting joints by name needs the skeleton")
            if not self.joint_names:
                raise ValueError("joints: expected at least one joint name")
            self._joints = torch.tensor([skeleton.joint_index(j) for j in self.joint_names])
        else:
            self._joints = None

    # ------------------------------------------------------------------ observation
    def prepare(self, frame) -> Joints2DObservation:
        """The frame's detections of the used joints, weights and evidence counts."""
        j2d = getattr(frame, "joints2d", frame)
        where = f"frame {getattr(frame, 'index', '?')}"
        if j2d is None:
            raise ValueError(f"joints2d: {where} has no 2D joint detections")
        if not isinstance(j2d, torch.Tensor) or j2d.dim() != 3 or j2d.shape[-1] != 3:
            shape = tuple(j2d.shape) if isinstance(j2d, torch.Tensor) else type(j2d).__name__
            raise ValueError(f"joints2d: expected shape (C, J, 3) (u, v, confidence), got {shape}")
        C, J = j2d.shape[:2]
        if C != self.rig.num_cameras:
            raise ValueError(f"joints2d: {C} cameras, the rig has {self.rig.num_cameras}")
        if self.skeleton is not None and J != self.skeleton.num_joints:
            raise ValueError(f"joints2d: {J} joints per camera, the skeleton has "
                             f"{self.skeleton.num_joints} (rows must follow its joint order)")
        idx = self._joints if self._joints is not None else torch.arange(J, device=j2d.device)
        if int(idx.max()) >= J:
            raise ValueError(f"joints2d: {J} joints per camera, a used joint has index "
                             f"{int(idx.max())}")
        sel = j2d.index_select(1, idx.to(j2d.device))
        uv, conf = sel[..., :2], sel[..., 2]
        finite = torch.isfinite(uv).all(-1) & torch.isfinite(conf)
        if bool((finite & (conf < 0)).any()):
            raise ValueError("joints2d: confidences must be >= 0")
        w = torch.where(finite & (conf > 0) & (conf >= self.min_confidence), conf,
                        torch.zeros_like(conf)).clamp(max=1.0)
        uv = torch.where(finite[..., None], uv, torch.zeros_like(uv))
        n = int((w > 0).sum())
        total = float(w.double().sum())
        if n == 0:
            if self.on_empty == "raise":
                raise EmptyEvidenceError(
                    f"joints2d: {where} has no valid 2D joint detection (every confidence is 0 "
                    f"or below min_confidence={self.min_confidence}); a frame without evidence "
                    "cannot be scored (on_empty='uninformative' gives it a constant energy)")
            return Joints2DObservation(uv, w, idx, 0, 0.0, empty=True)
        return Joints2DObservation(uv, w, idx, n, total)

    # ------------------------------------------------------------------ energy
    def energy(self, poses: Poses, observation: Joints2DObservation) -> torch.Tensor:
        return joints2d_energy(poses.kinematics.positions, observation, self.rig,
                               self.scale_px, self.robust, self.reduction)

    def gauss_newton(self, poses: Poses | torch.Tensor, observation: Joints2DObservation,
                     hessian: bool = True):
        """Energy, analytic gradient and Gauss–Newton Hessian.

        Args:
            poses: a :class:`Poses` or ``theta (P, D)`` (then the constructor's skeleton).
            observation: from :meth:`prepare`.
            hessian: also return ``H``.

        Returns:
            ``energy (P,)``, ``grad (P, D)`` and ``H (P, D, D)`` (``None`` when not asked).

        Raises:
            ValueError: a rig with lens distortion (the analytic derivatives are pinhole-only).
        """
        if isinstance(poses, Poses):
            theta, sk = poses.theta, poses.skeleton
        else:
            theta, sk = poses, self.skeleton
            if sk is None:
                raise ValueError("skeleton: needed to differentiate theta (pass Poses)")
        rig = self.rig
        if rig.has_distortion:
            raise ValueError("rig: the analytic 2D-joint derivatives support undistorted "
                             "pinhole cameras only (use autograd on the energy)")
        dt = theta.dtype
        P, D = theta.shape
        theta = theta.detach()
        if observation.empty:
            v = theta.new_full((P,), _empty_energy(observation, self.robust))
            return v, torch.zeros_like(theta), (theta.new_zeros(P, D, D) if hessian else None)
        kin, Jp, _ = sk.jacobian(theta)
        idx = observation.joints.to(theta.device)
        X = kin.positions.index_select(1, idx)  # (P, J', 3)
        JX = Jp.index_select(1, idx)  # (P, J', 3, D)
        K, R, t = rig.K.to(dt), rig.R.to(dt), rig.t.to(dt)
        xc = torch.einsum("cij,pnj->pcni", R, X) + t[None, :, None, :]  # (P, C, J', 3)
        depth = xc[..., 2]
        front = depth > _DEPTH_EPS
        z = depth.clamp_min(_DEPTH_EPS)
        x, y = xc[..., 0] / z, xc[..., 1] / z
        fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
        sk_, cx, cy = K[:, 0, 1, None], K[:, 0, 2, None], K[:, 1, 2, None]
        u = fx * x + sk_ * y + cx
        v = fy * y + cy
        r = torch.stack([u, v], -1) - observation.uv.to(dt)  # (P, C, J', 2)
        s2 = self.scale_px**2
        zz = (r * r).sum(-1) / s2
        rho, drho = robust_cost(zz, self.robust)
        w = observation.weight.to(dt)
        nf = _norm_factor(observation, self.reduction)
        energy = (w * rho).sum((-1, -2)) * nf
        # d(u, v) / d x_cam (P, C, J', 2, 3); a point behind the camera (clamped depth) has no
        # derivative through its depth, as the clamp in the projection
        inv = 1.0 / z
        dz = torch.where(front, inv, torch.zeros_like(inv))
        zero = torch.zeros_like(u)
        A = torch.stack([
            torch.stack([fx * inv, sk_ * inv, -(fx * x + sk_ * y) * dz], -1),
            torch.stack([zero, fy * inv, -fy * y * dz], -1),
        ], -2)
        A = A @ R[None, :, None]  # world -> pixels (P, C, J', 2, 3)
        Jpix = A @ JX[:, None]  # (P, C, J', 2, D)
        cw = w * drho * (2.0 * nf / s2)  # (P, C, J')
        grad = torch.einsum("pcn,pcnk,pcnkd->pd", cw, r, Jpix)
        H = None
        if hessian:
            H = torch.einsum("pcn,pcnkd,pcnke->pde", cw, Jpix, Jpix)
        return energy, grad, H

    def extra_repr(self) -> str:
        return (f"scale_px={self.scale_px}, robust={self.robust!r}, reduction="
                f"{self.reduction!r}, on_empty={self.on_empty!r}, joints="
                f"{'all' if self.joint_names is None else len(self.joint_names)}")
