"""A learned noise model of computed masks: per view a false-positive rate, a false-negative
rate and a boundary width.

Computed foreground masks have structured errors (a shadow, the treadmill, a bystander's edge,
a body part lost against a similar background). Per camera ``c`` the observed mask bit ``o`` of
a pixel is modelled as

    p(o = 1 | theta) = f_c + (1 - f_c - n_c) m_c(x; theta, w_c)

with ``m_c`` the capsule body's soft silhouette
(:func:`~torchmocap.likelihoods.soft_capsule_silhouettes`: the sigmoid of the pixel's coverage
margin over the boundary width ``w_c`` pixels), ``f_c`` the false-positive rate (background
marked foreground) and ``n_c`` the false-negative rate (body marked background). The energy is
the Bernoulli negative log-likelihood summed over every ``stride``-th pixel of every view the
frame did not drop::

    V(theta) = - sum_c sum_x [ o log p + (1 - o) log(1 - p) ]

The rates (as logits, kept in ``(0, 0.5)`` by a scaled sigmoid) and the log-widths are
``nn.Parameter``\\ s, frozen unless ``learn``; :func:`fit_noise_model` fits them to masks under
given poses (maximum likelihood, L-BFGS) — for a held-out camera, the rates of the training
views are averaged (:meth:`SilhouetteNoiseLikelihood.mean_parameters`).

Shapes: ``P`` poses, ``C`` cameras, ``h x w`` the subsampled pixel grid of a view.

Example:
    >>> from torchmocap.body import CapsuleBody
    >>> from torchmocap.cameras import make_ring_rig
    >>> from torchmocap.skeleton import human31
    >>> from torchmocap.likelihoods import FrameEnergy, render_capsule_silhouettes
    >>> from torchmocap.data import Frame
    >>> sk = human31(); body = CapsuleBody(sk).float(); rig = make_ring_rig(2).float()
    >>> th = sk.zero_pose((1,))
    >>> masks = render_capsule_silhouettes(body, rig, th[0])             # (C, H, W)
    >>> term = SilhouetteNoiseLikelihood(body, rig, stride=8)
    >>> V = FrameEnergy(term, term.prepare(Frame(0, 0.0, silhouettes=masks)), sk)
    >>> bool(V(th) < V(th + 0.3))
    True
"""

from __future__ import annotations

import math

import torch
from torch import nn

from torchmocap.likelihoods.base import Likelihood, Poses
from torchmocap.likelihoods.silhouette import soft_capsule_silhouettes

__all__ = ["SilhouetteNoiseLikelihood", "fit_noise_model"]

_MAX_RATE = 0.5  # rates live in (0, 0.5): a rate of 0.5 or more would invert the mask


def _logit(rate: float) -> float:
    return math.log(rate / (_MAX_RATE - rate))


class SilhouetteNoiseLikelihood(Likelihood):
    """Bernoulli likelihood of computed masks with per-view error rates and boundary width.

    Args:
        body: the :class:`~torchmocap.body.CapsuleBody` (runtime dependency).
        rig: the :class:`~torchmocap.cameras.CameraRig` of the masks (runtime dependency).
        false_positive: starting false-positive rate in ``(0, 0.5)`` (every view).
        false_negative: starting false-negative rate in ``(0, 0.5)``.
        width_px: starting boundary width in pixels of the masks (> 0).
        stride: every ``stride``-th pixel of each view is scored.
        learn: the parameters require gradients.

    Raises:
        ValueError: a bad setting (named).
    """

    requires = ("silhouettes",)

    def __init__(self, body, rig, false_positive: float = 0.05, false_negative: float = 0.05,
                 width_px: float = 1.0, stride: int = 4, learn: bool = False) -> None:
        super().__init__()
        for name, v in (("false_positive", false_positive),
                        ("false_negative", false_negative)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < _MAX_RATE:
                raise ValueError(f"{name}: expected a rate in (0, {_MAX_RATE}), got {v!r}")
        if isinstance(width_px, bool) or not isinstance(width_px, (int, float)) \
                or not (math.isfinite(width_px) and width_px > 0):
            raise ValueError(f"width_px: expected a number > 0, got {width_px!r}")
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ValueError(f"stride: expected an integer >= 1, got {stride!r}")
        C = rig.num_cameras
        self.body, self.rig, self.stride = body, rig, stride
        self.logit_fp = nn.Parameter(torch.full((C,), _logit(false_positive)),
                                     requires_grad=bool(learn))
        self.logit_fn = nn.Parameter(torch.full((C,), _logit(false_negative)),
                                     requires_grad=bool(learn))
        self.log_width = nn.Parameter(torch.full((C,), math.log(width_px)),
                                      requires_grad=bool(learn))

    def rates(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(C,)`` false-positive rates, false-negative rates and boundary widths (px)."""
        return (_MAX_RATE * torch.sigmoid(self.logit_fp),
                _MAX_RATE * torch.sigmoid(self.logit_fn), self.log_width.exp())

    def mean_parameters(self) -> dict[str, float]:
        """The views' rates and width averaged (in logit / log units): the parameters for a
        camera the model was not fitted to."""
        return {"false_positive": _MAX_RATE * float(torch.sigmoid(self.logit_fp.mean())),
                "false_negative": _MAX_RATE * float(torch.sigmoid(self.logit_fn.mean())),
                "width_px": float(self.log_width.mean().exp())}

    def prepare(self, frame) -> dict:
        """The frame's masks on each view's pixel grid (``(h, w)`` floats per view, cropped to
        the view's own size) and the views it did not drop."""
        masks = getattr(frame, "silhouettes", None)
        if masks is None:
            raise ValueError(f"silhouettes: frame {getattr(frame, 'index', '?')} has no masks")
        C = self.rig.num_cameras
        if masks.dim() != 3 or masks.shape[0] != C:
            raise ValueError(f"silhouettes: expected shape ({C}, H, W), got "
                             f"{tuple(masks.shape)}")
        grids = []
        for c in range(C):
            W, H = (int(v) for v in self.rig.image_size[c].tolist())
            grids.append(masks[c, :H:self.stride, :W:self.stride].float())
        dropped = getattr(frame, "view_dropped", None)
        valid = torch.ones(C, dtype=torch.bool) if dropped is None else ~dropped.bool().cpu()
        return {"masks": grids, "valid": valid}

    def view_probability(self, poses: Poses, c: int) -> torch.Tensor:
        """``(P, h, w)`` probability that each grid pixel of view ``c`` is marked foreground."""
        fp, fn, width = self.rates()
        soft = soft_capsule_silhouettes(poses.endpoints(self.body), self.body.radii,
                                        self.rig.subset([c]), self.stride, width[c])[:, 0]
        return fp[c] + (1.0 - fp[c] - fn[c]) * soft

    def energy(self, poses: Poses, observation: dict) -> torch.Tensor:
        total = None
        for c, o in enumerate(observation["masks"]):
            if not bool(observation["valid"][c]):
                continue
            p = self.view_probability(poses, c)
            o = o.to(p)[None, :p.shape[1], :p.shape[2]]
            nll = -(o * p.log() + (1.0 - o) * torch.log1p(-p)).sum((-1, -2))
            total = nll if total is None else total + nll
        if total is None:
            return poses.theta.new_zeros(poses.num) + 0.0 * poses.theta.sum(-1)
        return total

    def extra_repr(self) -> str:
        fp, fn, w = self.rates()
        return (f"false_positive={[round(float(v), 4) for v in fp]}, "
                f"false_negative={[round(float(v), 4) for v in fn]}, "
                f"width_px={[round(float(v), 2) for v in w]}, stride={self.stride}")


def fit_noise_model(term: SilhouetteNoiseLikelihood, skeleton, frames, theta: torch.Tensor,
                    iterations: int = 50) -> float:
    """Fit the rates and widths to the masks of ``frames`` (a list of
    :class:`~torchmocap.data.Frame`) under the poses ``theta (T, D)`` (maximum likelihood,
    L-BFGS; the poses are fixed). Returns the negative log-likelihood per scored pixel."""
    obs = [term.prepare(f) for f in frames]
    params = [term.logit_fp, term.logit_fn, term.log_width]
    for p in params:
        p.requires_grad_(True)
    n = sum(int(o["masks"][c].numel()) for o in obs for c in range(len(o["masks"]))
            if bool(o["valid"][c]))
    poses = [Poses(theta[t:t + 1].detach(), skeleton) for t in range(len(frames))]
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iterations, history_size=10,
                            line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = sum(term.energy(p, o).sum() for p, o in zip(poses, obs)) / max(n, 1)
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        value = float(sum(term.energy(p, o).sum() for p, o in zip(poses, obs))) / max(n, 1)
    for p in params:
        p.requires_grad_(False)
    return value
