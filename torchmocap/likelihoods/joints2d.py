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

Depth order (``occlusion="capsules"``): one view cannot tell a limb from its mirror image in
depth by the joints' positions, but a detector still shows which joints the body hides — it
misses them more often and reports them with a low confidence. A detection below
``occluded_below`` (or a missed joint) *reads as hidden*; the pose's capsule body predicts which
joints are hidden (the line of sight from the camera to the joint passes through a capsule other
than those the joint sits in or on, :func:`predicted_hidden`). Each in-image joint whose reading
disagrees with the prediction adds ``log((1 - e) / e)`` (``e = occlusion_error``, the chance that
the detector's cue is wrong): the negative log-likelihood ratio of a binary cue. The term is
piecewise constant in the pose (no gradient, no Hessian contribution): it separates modes the
residuals tie on, and a local optimiser only accepts steps that do not break it.

Shapes: ``P`` poses, ``D`` DoF, ``C`` cameras, ``J`` joints (``J'`` used ones), ``B`` capsules.

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
    "occlusion_energy",
    "predicted_hidden",
    "robust_cost",
    "weighted_robust_sum",
]

#: Depth-order models of :class:`Joints2DLikelihood` (``occlusion``).
OCCLUSION_MODELS = ("none", "capsules")

#: Names of the robust functions ``rho(z)`` (see the module docstring).
ROBUST_COSTS = ("cauchy", "geman_mcclure", "huber", "gaussian")
_HIDDEN_MARGIN = 0.05  # m of line of sight before a joint that cannot hide it
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
        hidden: ``(C, J')`` bool, detections that read as hidden (missed or below
            ``occluded_below``); None without a depth-order model.
    """

    uv: torch.Tensor
    weight: torch.Tensor
    joints: torch.Tensor
    num_valid: int
    total_weight: float
    empty: bool = False
    hidden: torch.Tensor | None = None


def _norm_factor(obs: Joints2DObservation, reduction: str) -> float:
    if obs.empty:
        return 0.0
    n = obs.num_valid if reduction == "sum" else 1
    return n / obs.total_weight


def _empty_energy(obs: Joints2DObservation, robust: str) -> float:
    slots = obs.weight.numel()
    return slots * float(robust_cost(torch.ones((), dtype=torch.float64), robust)[0])


def joints2d_energy(positions: torch.Tensor, observation: Joints2DObservation, rig,
                    scale_px: float | torch.Tensor = 4.0, robust: str = "cauchy",
                    reduction: str = "sum") -> torch.Tensor:
    """The robust 2D-joint energy of joint positions (module docstring).

    Args:
        positions: ``(P, J, 3)`` world joint centres (metres) of the skeleton's joints.
        observation: :class:`Joints2DObservation` (``Joints2DLikelihood.prepare``).
        rig: :class:`~torchmocap.cameras.CameraRig` with ``C`` cameras.
        scale_px: robust scale ``s`` in pixels: a number, or a ``(C,)`` tensor of one scale
            per camera (differentiable).
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
    if isinstance(scale_px, torch.Tensor):
        scale_px = scale_px.to(pix)[:, None]  # (C, 1): per camera
    return weighted_robust_sum(pix, observation.uv, observation.weight, scale_px, robust) \
        * _norm_factor(observation, reduction)


def weighted_robust_sum(pix: torch.Tensor, uv: torch.Tensor, weight: torch.Tensor,
                        scale_px: float | torch.Tensor, robust: str = "cauchy") -> torch.Tensor:
    """``sum_cj w_cj rho(|pix_cj - uv_cj|^2 / s_cj^2)`` over the last two axes (cameras,
    joints): the un-normalised sum of :func:`joints2d_energy`.

    Args:
        pix: ``(P, C, J, 2)`` projected model points (pixels).
        uv: ``(..., C, J, 2)`` detected pixels, broadcast against ``pix``.
        weight: ``(..., C, J)`` weights (0 = skipped: such a slot costs nothing, also where the
            model point projects to an infinite pixel).
        scale_px: ``s`` in pixels: a number or a tensor broadcast against ``(C, J)``.
        robust: one of :data:`ROBUST_COSTS`.

    Returns:
        ``(P,)`` sums (differentiable in ``pix``, ``weight`` and a tensor ``scale_px``).
    """
    r = pix - uv.to(pix)
    z = (r * r).sum(-1) / (scale_px * scale_px)
    rho, _ = robust_cost(z, robust)
    w = weight.to(pix)
    return torch.where(w > 0, w * rho, torch.zeros_like(rho)).sum((-1, -2))


def predicted_hidden(positions: torch.Tensor, joints: torch.Tensor, body, rig) -> torch.Tensor:
    """Which joints the capsule body hides from each camera.

    A joint is hidden when the segment from the camera centre to 5 cm before it passes through
    a capsule that is neither one of the joint's own parts
    (:func:`~torchmocap.body.parts.own_parts`; a capsule is carried by its bone's parent joint)
    nor a capsule the joint lies inside.

    Args:
        positions: ``(P, J, 3)`` joint centres of the body's skeleton.
        joints: ``(J',)`` int64 indices of the joints to test.
        body: :class:`~torchmocap.body.CapsuleBody` of the skeleton (``B`` capsules).
        rig: camera rig with ``C`` cameras.

    Returns:
        ``(P, C, J')`` bool.
    """
    from torchmocap.body.capsules import rays_blocked_by_capsules, segment_distance
    from torchmocap.body.parts import own_parts

    with torch.no_grad():
        ep = body.endpoints(positions)  # (P, B, 2, 3)
        joints = joints.to(positions.device)
        X = positions.index_select(-2, joints)  # (P, J', 3)
        radii = body.radii.to(positions)
        own = own_parts(body.skeleton.parents).to(joints.device)
        own = own[joints][:, body.parent_index.to(joints.device)]  # (J', B)
        ignore = own[None] | (segment_distance(X, ep) < radii)  # (P, J', B)
        hidden = rays_blocked_by_capsules(rig.camera_centers().to(positions), X, ep, radii,
                                          stop=_HIDDEN_MARGIN, ignore=ignore)  # (C, P, J')
        return hidden.transpose(0, 1)


def occlusion_energy(positions: torch.Tensor, observation: Joints2DObservation, rig, body,
                     error: float = 0.1) -> torch.Tensor:
    """The depth-order energy (module docstring): ``log((1 - e) / e)`` per in-image joint whose
    hidden/visible reading disagrees with the body's prediction.

    Args:
        positions: ``(P, J, 3)`` joint centres.
        observation: with ``hidden`` set (``Joints2DLikelihood(occlusion="capsules")``).
        rig: the camera rig.
        body: the :class:`~torchmocap.body.CapsuleBody`.
        error: ``e`` in ``(0, 0.5)``.

    Returns:
        ``(P,)`` energies (no gradient).
    """
    if observation.hidden is None:
        raise ValueError("observation: has no hidden/visible readings (prepare it with "
                         "occlusion='capsules')")
    P = positions.shape[0]
    if observation.empty:
        return positions.new_zeros(P)
    with torch.no_grad():
        pred = predicted_hidden(positions, observation.joints, body, rig)  # (P, C, J')
        X = positions.index_select(-2, observation.joints.to(positions.device))
        inside = rig.project(X)[2]  # (P, C, J') in front and in the image
        wrong = (pred != observation.hidden.to(pred.device)[None]) & inside
        return wrong.sum((-1, -2)).to(positions.dtype) * math.log((1.0 - error) / error)


def check_detection_settings(owner: str, rig, robust: str, reduction: str, on_empty: str,
                             min_confidence) -> None:
    """The settings a reprojection term of 2D detections shares (typed errors naming them)."""
    if rig is None:
        raise ValueError(f"rig: {owner} needs the camera rig of the detections")
    if robust not in ROBUST_COSTS:
        raise ValueError(f"robust: expected one of {ROBUST_COSTS}, got {robust!r}")
    if reduction not in ("sum", "mean"):
        raise ValueError(f"reduction: expected 'sum' or 'mean', got {reduction!r}")
    if on_empty not in ("raise", "uninformative"):
        raise ValueError(f"on_empty: expected 'raise' or 'uninformative', got {on_empty!r}")
    if isinstance(min_confidence, bool) or not (
            isinstance(min_confidence, (int, float)) and 0 <= min_confidence <= 1):
        raise ValueError(f"min_confidence: expected a number in [0, 1], got {min_confidence!r}")


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
        occlusion: depth-order model, ``"none"`` (default) or ``"capsules"`` (module
            docstring; needs ``body``).
        body: the tracker's :class:`~torchmocap.body.CapsuleBody` (runtime dependency).
        occlusion_error: ``e``, the chance that a detection's hidden/visible reading is wrong.
        occluded_below: confidence under which a detection reads as hidden.
    """

    requires = ("joints2d",)

    def __init__(self, rig, skeleton=None, scale_px: float = 4.0, robust: str = "cauchy",
                 joints: Sequence[str] | None = None, min_confidence: float = 0.0,
                 reduction: str = "sum", on_empty: str = "raise", occlusion: str = "none",
                 body=None, occlusion_error: float = 0.1, occluded_below: float = 0.55) -> None:
        super().__init__()
        check_detection_settings(type(self).__name__, rig, robust, reduction, on_empty,
                                 min_confidence)
        if not (isinstance(scale_px, (int, float)) and not isinstance(scale_px, bool)
                and math.isfinite(scale_px) and scale_px > 0):
            raise ValueError(f"scale_px: expected a finite number > 0, got {scale_px!r}")
        if occlusion not in OCCLUSION_MODELS:
            raise ValueError(f"occlusion: expected one of {OCCLUSION_MODELS}, got {occlusion!r}")
        if occlusion != "none" and body is None:
            raise ValueError("body: occlusion='capsules' needs the tracker's capsule body")
        if not (isinstance(occlusion_error, (int, float)) and 0 < occlusion_error < 0.5):
            raise ValueError(f"occlusion_error: expected a probability in (0, 0.5), got "
                             f"{occlusion_error!r}")
        if not (isinstance(occluded_below, (int, float)) and 0 < occluded_below <= 1):
            raise ValueError(f"occluded_below: expected a confidence in (0, 1], got "
                             f"{occluded_below!r}")
        self.occlusion = occlusion
        self.body = body if occlusion != "none" else None
        self.occlusion_error = float(occlusion_error)
        self.occluded_below = float(occluded_below)
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
        hidden = None
        if self.occlusion != "none":
            hidden = ~(finite & (conf >= self.occluded_below))
        if n == 0:
            if self.on_empty == "raise":
                raise EmptyEvidenceError(
                    f"joints2d: {where} has no valid 2D joint detection (every confidence is 0 "
                    f"or below min_confidence={self.min_confidence}); a frame without evidence "
                    "cannot be scored (on_empty='uninformative' gives it a constant energy)")
            return Joints2DObservation(uv, w, idx, 0, 0.0, empty=True, hidden=hidden)
        return Joints2DObservation(uv, w, idx, n, total, hidden=hidden)

    # ------------------------------------------------------------------ energy
    def energy(self, poses: Poses, observation: Joints2DObservation) -> torch.Tensor:
        pos = poses.kinematics.positions
        v = joints2d_energy(pos, observation, self.rig, self.scale_px, self.robust,
                            self.reduction)
        return v + self._occlusion(pos, observation)

    def _occlusion(self, positions: torch.Tensor, observation: Joints2DObservation):
        if self.body is None or observation.hidden is None:
            return 0.0
        v = occlusion_energy(positions.detach(), observation, self.rig, self.body,
                             self.occlusion_error)
        if self.reduction == "mean":
            v = v / max(1, observation.hidden.numel())
        return v

    def offers_gauss_newton(self, observation: Joints2DObservation) -> bool:
        """Analytic derivatives for undistorted pinhole cameras."""
        return not self.rig.has_distortion

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
        energy = (w * rho).sum((-1, -2)) * nf + self._occlusion(kin.positions, observation)
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
                f"{self.reduction!r}, on_empty={self.on_empty!r}, occlusion="
                f"{self.occlusion!r}, joints="
                f"{'all' if self.joint_names is None else len(self.joint_names)}")
