"""Learned term: a small CNN compares the observed mask with a soft rendering of the capsules.

Per particle and view, the capsule model is rendered differentiably on a coarse grid of
``size = (w, h)`` cells covering the whole image (:func:`soft_render_capsules`: the sigmoid of
each cell centre's coverage margin, the stadium model of
:mod:`~torchmocap.likelihoods.silhouette`), and the observed mask is area-averaged onto the same
grid once per frame. The CNN reads the three planes ``[rendered, observed, rendered x
observed]`` (strided 3x3 convolutions, SiLU), pools each view's feature map by mean and max,
pools the views by mean and max over those not dropped, and a head MLP gives the energy
``(P,)``. The grid is fixed in cells, not pixels, so the same network runs on any image size (the
320x240 synthetic rigs, the real 640x480 bodytrack frame).

Rendering costs ``O(P C B w h)``: at 64x48 cells it is meant for few particles (local descent,
one-frame fits, reranking); for 200-particle annealing use a coarser grid or
:class:`~torchmocap.likelihoods.learned_features.LearnedFeatureLikelihood`.
Shapes: ``P`` particles, ``C`` views, ``B`` capsules.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from torchmocap.likelihoods.learned import LearnedLikelihood, mlp, pool_views
from torchmocap.likelihoods.silhouette import _coverage_margin, _stadiums, prepare_silhouettes

__all__ = ["LearnedRenderLikelihood", "RenderNet", "RenderObservation", "downsample_masks",
           "soft_render_capsules"]


def _image_size(rig) -> tuple[int, int]:
    sizes = {tuple(int(v) for v in sz) for sz in rig.image_size.tolist()}
    if len(sizes) != 1:
        raise ValueError(f"rig: all cameras need one image size, got {sorted(sizes)}")
    return sizes.pop()


def soft_render_capsules(endpoints: torch.Tensor, radii: torch.Tensor, rig,
                         size: tuple[int, int] = (64, 48), tau: float = 0.5) -> torch.Tensor:
    """Soft silhouettes ``(P, C, h, w)`` in [0, 1] of capsules ``endpoints (P, B, 2, 3)``
    (radii ``(B,)``) on a grid of ``size = (w, h)`` cells over the whole image.

    Cell ``(i, j)`` is centred on the image point ``((j + 0.5) W / w - 0.5,
    (i + 0.5) H / h - 0.5)``; its value is ``sigmoid(margin / (tau W / w))`` with ``margin`` the
    largest coverage margin ``r(t) − d`` (image pixels) over the capsules, so ``tau`` is in cells.
    Differentiable in the endpoints and radii (and twice: an unrolled optimiser may differentiate
    through it).

    Example:
        >>> from torchmocap import body, cameras, skeleton
        >>> sk = skeleton.human31(); capsules = body.CapsuleBody(sk).float()
        >>> ends = capsules.endpoints(sk(sk.zero_pose((2,))))
        >>> rig = cameras.make_ring_rig(4).float()
        >>> soft_render_capsules(ends, capsules.radii, rig, (32, 24)).shape
        torch.Size([2, 4, 24, 32])
    """
    if endpoints.dim() != 4 or endpoints.shape[-2:] != (2, 3):
        raise ValueError(f"endpoints: expected shape (P, B, 2, 3), got {tuple(endpoints.shape)}")
    w, h = (int(s) for s in size)
    if w < 1 or h < 1:
        raise ValueError(f"size: expected two ints >= 1 (w, h), got {size!r}")
    if not tau > 0:
        raise ValueError(f"tau: expected a value > 0 (cells), got {tau!r}")
    W, H = _image_size(rig)
    st = _stadiums(endpoints, radii, rig)
    dt = st.ax.dtype
    sx, sy = W / w, H / h
    xs = (torch.arange(w, dtype=dt, device=st.ax.device) + 0.5) * sx - 0.5
    ys = (torch.arange(h, dtype=dt, device=st.ax.device) + 0.5) * sy - 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    q = torch.stack([gx, gy], -1).reshape(1, -1, 2)
    C, P = st.ax.shape[0], endpoints.shape[0]
    margin = _coverage_margin(q.expand(C, -1, -1), st, smooth=True)  # (C, h w, P)
    soft = torch.sigmoid(margin / (tau * 0.5 * (sx + sy)))
    return soft.permute(2, 0, 1).reshape(P, C, h, w)


def downsample_masks(masks: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Area-average ``masks (C, H, W)`` (0/1) onto ``size = (w, h)`` cells: ``(C, h, w)``."""
    w, h = (int(s) for s in size)
    return F.adaptive_avg_pool2d(masks[:, None].float(), (h, w))[:, 0]


class RenderNet(nn.Module):
    """The parameters of :class:`LearnedRenderLikelihood`: ``len(channels)`` strided 3x3
    convolutions and a head MLP."""

    def __init__(self, channels: tuple[int, ...] | list[int] = (8, 16, 16), hidden: int = 16):
        super().__init__()
        layers: list[nn.Module] = []
        cin = 3
        for c in channels:
            layers += [nn.Conv2d(cin, c, 3, stride=2, padding=1), nn.SiLU()]
            cin = c
        self.conv = nn.Sequential(*layers)
        self.head = mlp([4 * cin, hidden, 1], final_bias=False)  # energies are shift-free

    def forward(self, rendered: torch.Tensor, observed: torch.Tensor,
                view_valid: torch.Tensor) -> torch.Tensor:
        """``rendered (P, C, h, w)``, ``observed (C, h, w)``, ``view_valid (C,)`` -> ``(P,)``."""
        P, C, h, w = rendered.shape
        if not bool(view_valid.any()):  # no evidence: one energy for every particle
            z = rendered.new_zeros(1, self.head[0].in_features)
            return self.head(z)[:, 0].expand(P)
        obs = observed.to(rendered.dtype)[None].expand(P, C, h, w)
        x = torch.stack([rendered, obs, rendered * obs], 2).reshape(P * C, 3, h, w)
        f = self.conv(x)
        f = torch.cat([f.mean((2, 3)), f.amax((2, 3))], -1).view(P, C, -1)
        return self.head(pool_views(f, view_valid))[:, 0]


@dataclass
class RenderObservation:
    """One frame prepared for :class:`LearnedRenderLikelihood`: ``observed (C, h, w)`` mask
    coverage of every cell, ``view_valid (C,)``."""

    observed: torch.Tensor
    view_valid: torch.Tensor


class LearnedRenderLikelihood(LearnedLikelihood):
    """Learned energy of a CNN comparing soft-rendered capsules with the observed masks.

    Args:
        body, rig: runtime dependencies.
        weights: weights file, ``"bundled"`` or ``None`` (random initialisation).
        size: render grid ``(w, h)`` in cells (the whole image).
        tau: soft-edge width of the rendering (cells).
        channels: convolution channels (each layer halves the grid).
        hidden: head width.
        net: an existing :class:`RenderNet` to share.
    """

    requires = ("silhouettes",)
    bundled = "learned_render.pt"

    def __init__(self, body, rig, weights: str | None = None,
                 size: tuple[int, int] | list[int] = (64, 48), tau: float = 0.5,
                 channels: tuple[int, ...] | list[int] = (8, 16, 16), hidden: int = 16,
                 net: RenderNet | None = None) -> None:
        super().__init__()
        size = [int(s) for s in size]
        if len(size) != 2 or min(size) < 4:
            raise ValueError(f"size: expected (w, h) with both >= 4 cells, got {size!r}")
        channels = [int(c) for c in channels]
        if not channels or min(channels) < 1:
            raise ValueError(f"channels: expected a non-empty list of ints >= 1, got "
                             f"{channels!r}")
        if not tau > 0:
            raise ValueError(f"tau: expected a value > 0, got {tau!r}")
        self.body, self.rig = body, rig
        self.size, self.tau, self.channels, self.hidden = size, float(tau), channels, int(hidden)
        self.net = RenderNet(channels, hidden).to(body.radii.dtype) if net is None else net
        self._init_weights(weights)

    @property
    def config(self) -> dict[str, Any]:
        return {"size": list(self.size), "tau": self.tau, "channels": list(self.channels),
                "hidden": self.hidden}

    def prepare(self, frame) -> RenderObservation:
        view_valid = None
        if getattr(frame, "view_dropped", None) is not None:
            view_valid = ~frame.view_dropped.bool()
        # the mask contract and empty views as in the silhouette term
        sil = prepare_silhouettes(frame.silhouettes, 1, blur=0.0, view_valid=view_valid)
        return RenderObservation(downsample_masks(sil.masks, self.size).to(self._net_dtype()),
                                 sil.view_valid)

    def evidence(self, observation: RenderObservation) -> bool:
        return bool(observation.view_valid.any())

    def render(self, poses) -> torch.Tensor:
        """Soft silhouettes ``(P, C, h, w)`` of ``poses``."""
        return soft_render_capsules(poses.endpoints(self.body), self.body.radii, self.rig,
                                    self.size, self.tau)

    def energy(self, poses, observation: RenderObservation) -> torch.Tensor:
        return self.net(self.render(poses), observation.observed, observation.view_valid)

    def extra_repr(self) -> str:
        return (f"size={self.size}, tau={self.tau}, channels={self.channels}, "
                f"weights={self.weights_path}")
