"""Fitting the capsule body to the subject's observed silhouettes at the start of a track.

The tracking model's capsule radii are anthropometric guesses; the observed person is thicker or
thinner (against the skinned CC0 mesh the default capsules overlap with IoU ≈ 0.77, so the
likelihood's optimum is not the true pose). :class:`SilhouetteBodyFit` adjusts the radius of
every capsule — one log-scale per body segment, left and right tied — so that the capsules at
the known first pose match the first frame's silhouettes: it maximises the soft
intersection-over-union of the differentiable capsule silhouettes
(:func:`~torchmocap.likelihoods.silhouette.soft_capsule_silhouettes`, every ``stride``-th pixel)
and the masks with Adam, within ``[min_scale, max_scale]`` of the initial radii. (The silhouette
*energy* is not used as the objective: its two normalised directions reward over-wide capsules —
at the true pose its optimum lowers the IoU from 0.78 to 0.70.) Bone lengths are the subject's
(fitted to the motion capture or scaled to the visual hull) and are not changed. The body is
updated in place, so every likelihood term that holds it sees the fitted radii.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from torchmocap.likelihoods.silhouette import (
    prepare_silhouettes,
    render_capsule_silhouettes,
    silhouette_energy,
    silhouette_iou,
    soft_capsule_silhouettes,
)

__all__ = ["SilhouetteBodyFit"]


def _segment(name: str) -> str:
    for side in ("l_", "r_"):
        if name.startswith(side):
            return name[len(side):]
    return name


class SilhouetteBodyFit(nn.Module):
    """Fit per-segment capsule radii to one frame's silhouettes at a known pose.

    Args:
        body: the runtime :class:`~torchmocap.body.CapsuleBody` (changed in place).
        rig: the cameras of the silhouettes.
        iterations: Adam steps.
        lr: step size (in log-radius).
        min_scale, max_scale: bounds of each radius relative to its initial value.
        symmetric: one scale for a left/right pair of segments.
        stride: pixel stride of the soft IoU.
        tau: softness (pixels) of the soft silhouettes (small: a wide sigmoid biases thin limbs
            towards thicker capsules).
        prior_weight: pull of every log-scale towards 0 (holds segments the silhouettes do not
            see, e.g. capsules hidden inside the torso).
        fg_samples: foreground pixels per view of the silhouette energy that is reported.

    ``forward(theta (D,), frame) -> info`` with ``iou_before``/``iou_after`` (mean over views),
    ``energy_before``/``energy_after`` and the fitted ``scales`` per segment.
    """

    def __init__(self, body, rig, iterations: int = 60, lr: float = 0.05,
                 min_scale: float = 0.6, max_scale: float = 1.8, symmetric: bool = True,
                 stride: int = 1, tau: float = 0.15, prior_weight: float = 0.02,
                 fg_samples: int = 400) -> None:
        super().__init__()
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
            raise ValueError(f"iterations: expected an int >= 0, got {iterations!r}")
        if not (0 < min_scale <= 1 <= max_scale and math.isfinite(max_scale)):
            raise ValueError(f"min_scale, max_scale: expected 0 < min_scale <= 1 <= max_scale, "
                             f"got {min_scale}, {max_scale}")
        if not (isinstance(lr, (int, float)) and lr > 0):
            raise ValueError(f"lr: expected a number > 0, got {lr!r}")
        self.body, self.rig = body, rig
        self.iterations, self.lr = iterations, float(lr)
        self.min_scale, self.max_scale = float(min_scale), float(max_scale)
        self.fg_samples = int(fg_samples)
        self.stride, self.tau = int(stride), float(tau)
        self.prior_weight = float(prior_weight)
        names = [_segment(n) if symmetric else n for n in body.bone_names]
        self.segments = list(dict.fromkeys(names))
        self.register_buffer("segment_index", torch.tensor([self.segments.index(n)
                                                            for n in names]))

    def forward(self, theta: torch.Tensor, frame) -> dict:
        if getattr(frame, "silhouettes", None) is None:
            raise ValueError("frame: the body fit needs silhouettes")
        body, rig = self.body, self.rig
        dt = body.radii.dtype
        valid = None
        if getattr(frame, "view_dropped", None) is not None:
            valid = ~frame.view_dropped.bool()
        hard = prepare_silhouettes(frame.silhouettes, self.fg_samples, blur=0.0,
                                   view_valid=valid, dtype=dt)
        r0 = body.radii.detach().clone()
        with torch.no_grad():
            ends = body.endpoints(body.skeleton(theta.to(dt)[None], check_finite=False))

        def energy(radii, obs, smooth_):
            return silhouette_energy(ends, radii, rig, obs, smooth=smooth_)[0]

        st = self.stride
        target = frame.silhouettes[:, ::st, ::st].to(dt)  # (C, H', W')
        vw = torch.ones(target.shape[0], dtype=dt) if valid is None else valid.to(dt)

        def soft_iou(radii):
            m = soft_capsule_silhouettes(ends, radii, rig, stride=st, tau=self.tau)[0]
            inter = (m * target).flatten(1).sum(-1)
            union = (m + target - m * target).flatten(1).sum(-1).clamp_min(1.0)
            return ((inter / union) * vw).sum() / vw.sum().clamp_min(1.0)

        def set_radii(radii):
            body.end_shrink.copy_(torch.where(body.end_shrink > 0, radii,
                                              torch.zeros_like(radii)))
            body.radii.copy_(radii)

        def iou(radii):
            set_radii(radii)
            model = render_capsule_silhouettes(body, rig, theta.to(dt))
            v = silhouette_iou(model, frame.silhouettes)
            keep = torch.ones_like(v, dtype=torch.bool) if valid is None else valid.to(v.device)
            return float(v[keep].mean()) if bool(keep.any()) else float("nan")

        with torch.no_grad():
            e0 = float(energy(r0, hard, False))
        iou0 = iou(r0)
        log_s = torch.zeros(len(self.segments), dtype=dt, requires_grad=True)
        lo, hi = math.log(self.min_scale), math.log(self.max_scale)
        opt = torch.optim.Adam([log_s], lr=self.lr)
        with torch.no_grad():
            start = float(soft_iou(r0))
        best, best_v = log_s.detach().clone(), start
        for _ in range(self.iterations):
            opt.zero_grad()
            with torch.enable_grad():
                v = soft_iou(r0 * log_s[self.segment_index].exp())
                (self.prior_weight * log_s.square().mean() - v).backward()
            opt.step()
            with torch.no_grad():
                log_s.clamp_(lo, hi)
                v = float(soft_iou(r0 * log_s[self.segment_index].exp()))
            if v > best_v:
                best, best_v = log_s.detach().clone(), v
        radii = r0 * best[self.segment_index].exp()
        with torch.no_grad():
            e1 = float(energy(radii, hard, False))
        iou1 = iou(radii.detach())  # leaves the fitted radii in the body
        return {"iou_before": iou0, "iou_after": iou1, "energy_before": e0,
                "energy_after": e1,
                "scales": {n: round(float(math.exp(float(best[i]))), 4)
                           for i, n in enumerate(self.segments)}}

    def extra_repr(self) -> str:
        return (f"iterations={self.iterations}, scale=[{self.min_scale}, {self.max_scale}], "
                f"segments={len(self.segments)}")
