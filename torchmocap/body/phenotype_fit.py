"""Fitting a subject's phenotype and segment scales to 3D joints of a few frames.

The body's joints are the skeleton's forward kinematics with the body's offsets
(:meth:`~torchmocap.body.ParametricBody.offsets`: the phenotype's joint centres, bone lengths
times segment scales), so observed joint positions ``x (T, J, 3)`` of the first frames constrain
the phenotype through a differentiable term::

    E(φ, s, θ) = mean_{t,j} w_j ‖FK(θ_t; offsets(φ, s))_j − x_tj‖² + λ mean_b (log s_b)²

minimised jointly over the phenotype ``φ = sigmoid(z)`` (in (0, 1)), the log segment scales
(left and right tied by default) and the frames' poses ``θ_t`` (from ``theta_init``: e.g. a
tracker's first estimates) with Adam. The scale prior ``λ`` makes the phenotype explain the bone
lengths and the scales only the rest; joints say nothing about girth (weight, muscle), which
silhouettes would add.

Shapes: ``T`` frames, ``J`` joints, ``D`` DoF.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["PhenotypeFit", "fit_phenotype", "standing_height"]


@dataclass
class PhenotypeFit:
    """Result of :func:`fit_phenotype`.

    Attributes:
        phenotype: ``(6,)`` fitted phenotype; segment_scales ``(S,)``; theta ``(T, D)``.
        joint_rmse: root-mean-square joint error (metres) at the end.
        height: the fitted body's standing height (:func:`standing_height`, metres).
        iterations: Adam steps run.
    """

    phenotype: Tensor
    segment_scales: Tensor
    theta: Tensor
    joint_rmse: float
    height: float
    iterations: int


def standing_height(body, phenotype=None, segment_scales=None) -> Tensor:
    """Vertical extent ``(*,)`` of the body standing in the skeleton's rest pose (arms down,
    legs straight) with its phenotype and segment scales (metres)."""
    phen = body.phenotype_tensor(phenotype)
    theta = body.skeleton.zero_pose(phen.shape[:-1], dtype=phen.dtype, device=phen.device)
    z = body(theta, phen, segment_scales=segment_scales).vertices[..., 2]
    return z.amax(-1) - z.amin(-1)


def _symmetric_index(bones: list[str]) -> tuple[list[int], int]:
    """Per bone the index of its scale when left and right share one, and their count."""
    key = [b[2:] if b[:2] in ("l_", "r_") else b for b in bones]
    uniq = list(dict.fromkeys(key))
    return [uniq.index(k) for k in key], len(uniq)


def fit_phenotype(body, joints: Tensor, theta_init: Tensor | None = None,
                  fit_scales: bool = True, symmetric: bool = True, scale_prior: float = 1e-2,
                  iterations: int = 400, lr: float = 0.05, pose_lr: float = 0.02,
                  joint_weights: Tensor | None = None,
                  phenotype_init: Tensor | None = None) -> PhenotypeFit:
    """Fit the phenotype (and segment scales, poses) of ``body`` to 3D joints (module doc).

    Args:
        body: a :class:`~torchmocap.body.ParametricBody`.
        joints: ``(T, J, 3)`` observed positions of the skeleton's joints (metres).
        theta_init: ``(T, D)`` starting poses (default: the rest pose moved to each frame's
            pelvis).
        fit_scales: fit segment scales too (else 1).
        symmetric: one scale per left/right pair.
        scale_prior: ``λ``, per squared log scale, against the mean squared joint error (m²):
            1e-2: a 10% scale (log² ≈ 0.009) costs as much as a 1 cm RMS joint error.
        iterations, lr, pose_lr: Adam steps and learning rates (phenotype logits and log
            scales; poses).
        joint_weights: ``(J,)`` optional weights of the joints.
        phenotype_init: ``(6,)`` starting phenotype (default 0.5 each).

    Returns:
        :class:`PhenotypeFit`.

    Raises:
        ValueError: naming ``joints`` or ``theta_init`` on a wrong shape or non-finite values.
    """
    sk = body.skeleton
    J = len(body.joint_names)
    if joints.dim() != 3 or joints.shape[1:] != (J, 3):
        raise ValueError(f"joints: expected shape (T, {J}, 3), got {tuple(joints.shape)}")
    if not bool(torch.isfinite(joints).all()):
        raise ValueError("joints: expected finite positions")
    T = joints.shape[0]
    dt, dev = joints.dtype, joints.device
    if theta_init is None:
        theta_init = sk.zero_pose((T,), dtype=dt, device=dev)
        rest_pelvis = body.offsets()[0].to(dt)
        theta_init[:, :3] = joints[:, 0] - rest_pelvis
    elif theta_init.shape != (T, sk.num_dofs):
        raise ValueError(f"theta_init: expected shape ({T}, {sk.num_dofs}), got "
                         f"{tuple(theta_init.shape)}")
    w = torch.ones(J, dtype=dt, device=dev) if joint_weights is None else \
        joint_weights.to(dt)
    p0 = torch.full((6,), 0.5, dtype=dt, device=dev) if phenotype_init is None else \
        phenotype_init.to(dt).clamp(1e-3, 1 - 1e-3)
    z = torch.logit(p0).clone().requires_grad_(True)
    index, n = _symmetric_index(body.bone_names) if symmetric else \
        (list(range(body.num_bones)), body.num_bones)
    log_s = torch.zeros(n, dtype=dt, device=dev, requires_grad=fit_scales)
    theta = theta_init.detach().to(dt).clone().requires_grad_(True)
    groups = [{"params": [z], "lr": lr}, {"params": [theta], "lr": pose_lr}]
    if fit_scales:
        groups.append({"params": [log_s], "lr": lr * 0.2})
    opt = torch.optim.Adam(groups)
    idx = torch.tensor(index, device=dev)

    def energy():
        phen = torch.sigmoid(z)
        s = log_s.exp()[idx]
        off = body.offsets(phen, s)
        pos = sk(theta, offsets=off, check_finite=False).positions
        err = ((pos - joints) ** 2).sum(-1)  # (T, J)
        data = (err * w).mean() / w.mean()
        return data + scale_prior * (log_s ** 2).mean(), err

    for _ in range(iterations):
        opt.zero_grad()
        e, _ = energy()
        e.backward()
        opt.step()
        with torch.no_grad():
            z.clamp_(-8, 8)
            log_s.clamp_(-0.5, 0.5)
    with torch.no_grad():
        _, err = energy()
        phen = torch.sigmoid(z)
        s = log_s.exp()[idx]
        height = float(standing_height(body, phen, s))
    return PhenotypeFit(phen.detach(), s.detach(), theta.detach(),
                        float(err.mean().sqrt()), height, iterations)
