"""Learned silhouette/appearance term on features sampled at the projected body.

For every particle the body-fixed surface pattern of the capsules (``axial x around`` points per
capsule, :func:`~torchmocap.likelihoods.body_surface_pattern`) is projected into every view, and
the observation is read there; every sampled foreground pixel is compared with the projected
capsules. Per view and point the features are

- surface point ``(P, C, N)``: the observed mask blurred at two widths (``blur``), whether the
  point faces the camera and lies in the image, the squared deviation of its colour from the
  point's mean colour over the views that see it (the appearance cue of V_app), the fraction of
  views that see it, and a learned embedding of its capsule;
- foreground pixel ``(P, C, G)``: the coverage margin of the pixel by the projected capsules
  (pixels, positive inside; the quantity of V_silh's image -> model term) through sigmoids of two
  widths and a ``tanh``.

Two small MLPs map each point's and each pixel's features to ``hidden`` channels, which are
averaged per view; a view is the concatenation of both means. Views are pooled by mean and max
over the views that are not dropped (:func:`~torchmocap.likelihoods.learned.pool_views`), and a
head MLP gives the energy ``(P,)``. With every view dropped all particles get the same energy
(the head of zeros): no evidence. The network sees no image coordinates and no subject size, so
one network serves every rig and subject (:meth:`LearnedLikelihood.bind`).

The hand-crafted ``V_silh`` is a special case (the mean mask at the points and the mean coverage
of the pixels, combined linearly), so training starts from a family that contains it.
Shapes: ``P`` particles, ``C`` views, ``B`` capsules, ``N`` surface points, ``G`` foreground
samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from torchmocap.likelihoods.appearance import _per_bone, body_surface_pattern
from torchmocap.likelihoods.learned import (
    LearnedLikelihood,
    bilinear_lookup,
    mlp,
    pool_views,
)
from torchmocap.likelihoods.silhouette import (
    _blur,
    _coverage_margin,
    _stadiums,
    prepare_silhouettes,
)

__all__ = ["FeatureNet", "FeatureObservation", "LearnedFeatureLikelihood", "POINT_FEATURES",
           "PIXEL_FEATURES"]

#: Per (view, surface point) input features (before the capsule embedding).
POINT_FEATURES = 6
#: Per (view, foreground pixel) input features.
PIXEL_FEATURES = 3


class FeatureNet(nn.Module):
    """The parameters of :class:`LearnedFeatureLikelihood`: point MLP, pixel MLP, capsule
    embedding and head (``hidden`` channels, ``depth`` hidden layers per MLP)."""

    def __init__(self, num_capsules: int, hidden: int = 16, depth: int = 1, embed: int = 4):
        super().__init__()
        h = [hidden] * depth
        self.embedding = nn.Embedding(num_capsules, embed)
        nn.init.normal_(self.embedding.weight, std=0.1)
        self.point = mlp([POINT_FEATURES + embed, *h, hidden])
        self.pixel = mlp([PIXEL_FEATURES, *h, hidden])
        self.head = mlp([4 * hidden, *h, 1], final_bias=False)  # energies are shift-free

    def forward(self, point_feats: torch.Tensor, bone: torch.Tensor, pixel_feats: torch.Tensor,
                pixel_valid: torch.Tensor, view_valid: torch.Tensor) -> torch.Tensor:
        """``point_feats (P, C, N, 6)``, ``bone (N,)``, ``pixel_feats (P, C, G, 3)``,
        ``pixel_valid (C, G)``, ``view_valid (C,)`` -> energy ``(P,)``."""
        P, C, N, _ = point_feats.shape
        if not bool(view_valid.any()):  # no evidence: one energy for every particle
            z = point_feats.new_zeros(1, self.head[0].in_features)
            return self.head(z)[:, 0].expand(P)
        emb = self.embedding(bone).to(point_feats.dtype)  # (N, E)
        first = self.point[0]  # the embedding's share of the first layer, once per capsule
        k = point_feats.shape[-1]
        h = F.linear(point_feats, first.weight[:, :k]) + F.linear(emb, first.weight[:, k:],
                                                                  first.bias)
        pt = self.point[1:](h).mean(2)  # (P, C, H)
        fv = pixel_valid.to(pixel_feats.dtype)[None, :, :, None]
        px = (self.pixel(pixel_feats) * fv).sum(2) / fv.sum(2).clamp_min(1)  # (P, C, H)
        pooled = pool_views(torch.cat([pt, px], -1), view_valid)  # (P, 4H)
        return self.head(pooled)[:, 0]


@dataclass
class FeatureObservation:
    """One frame prepared for :class:`LearnedFeatureLikelihood`.

    Attributes:
        planes: ``(C, 2 + 3, H, W)``: the mask blurred at the two widths, colour in [0, 1]
            (zeros without images).
        fg_pixels: ``(C, G, 2)`` sampled foreground pixel centres; fg_valid: ``(C, G)``.
        view_valid: ``(C,)`` views that are neither dropped nor empty.
        has_colour: whether ``planes`` holds colour.
    """

    planes: torch.Tensor
    fg_pixels: torch.Tensor
    fg_valid: torch.Tensor
    view_valid: torch.Tensor
    has_colour: bool


class LearnedFeatureLikelihood(LearnedLikelihood):
    """Learned energy on mask/colour features at the projected body (module docstring).

    Args:
        body: the :class:`~torchmocap.body.CapsuleBody` of the subject.
        rig: the :class:`~torchmocap.cameras.CameraRig` of the observations.
        weights: weights file, ``"bundled"`` or ``None`` (random initialisation).
        hidden, depth, embed: network size (channels, hidden layers per MLP, capsule
            embedding size).
        axial, around: surface points per capsule.
        fg_samples: foreground pixels per view.
        blur: the two mask blur widths (pixels).
        use_colour: read the colour images (``requires`` then includes ``"images"``); without,
            the colour features are zero.
        net: an existing :class:`FeatureNet` to share (training on many sequences).

    Example:
        >>> from torchmocap.body import CapsuleBody
        >>> from torchmocap.cameras import make_ring_rig
        >>> from torchmocap.skeleton import human31
        >>> sk = human31(); body = CapsuleBody(sk).float()
        >>> term = LearnedFeatureLikelihood(body, make_ring_rig(4).float(), use_colour=False)
        >>> " ".join(sorted(term.config)[:3])
        'around axial blur'
    """

    bundled = "learned_features.pt"

    def __init__(self, body, rig, weights: str | None = None, hidden: int = 8, depth: int = 1,
                 embed: int = 4, axial: int = 2, around: int = 3, fg_samples: int = 32,
                 blur: tuple[float, float] | list[float] = (1.0, 3.0), use_colour: bool = True,
                 net: FeatureNet | None = None) -> None:
        super().__init__()
        for name, v, lo in (("hidden", hidden, 1), ("depth", depth, 0), ("embed", embed, 1),
                            ("axial", axial, 1), ("around", around, 1),
                            ("fg_samples", fg_samples, 1)):
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"{name}: expected an int >= {lo}, got {v!r}")
        blur = [float(b) for b in blur]
        if len(blur) != 2 or min(blur) < 0:
            raise ValueError(f"blur: expected two widths >= 0 (pixels), got {blur!r}")
        self.body, self.rig = body, rig
        self.hidden, self.depth, self.embed = hidden, depth, embed
        self.axial, self.around, self.fg_samples = axial, around, fg_samples
        self.blur, self.use_colour = blur, bool(use_colour)
        self.requires = ("silhouettes", "images") if self.use_colour else ("silhouettes",)
        self.pattern = body_surface_pattern(body, axial, around)
        B = int(body.radii.shape[0])
        if net is None:
            net = FeatureNet(B, hidden, depth, embed).to(body.radii.dtype)
        elif net.embedding.num_embeddings != B:
            raise ValueError(f"net: built for {net.embedding.num_embeddings} capsules, the body "
                             f"has {B}")
        self.net = net
        self._init_weights(weights)

    @property
    def config(self) -> dict[str, Any]:
        return {"hidden": self.hidden, "depth": self.depth, "embed": self.embed,
                "axial": self.axial, "around": self.around, "fg_samples": self.fg_samples,
                "blur": list(self.blur), "use_colour": self.use_colour,
                "num_capsules": int(self.body.radii.shape[0])}

    def bind(self, body, rig) -> LearnedFeatureLikelihood:
        cfg = {k: v for k, v in self.config.items() if k != "num_capsules"}
        return LearnedFeatureLikelihood(body, rig, net=self.net, **cfg)

    # ------------------------------------------------------------------ per frame
    def prepare(self, frame) -> FeatureObservation:
        dt = self._net_dtype()
        view_valid = None
        if getattr(frame, "view_dropped", None) is not None:
            view_valid = ~frame.view_dropped.bool()
        sil = prepare_silhouettes(frame.silhouettes, self.fg_samples, blur=0.0,
                                  view_valid=view_valid, dtype=dt)
        m = sil.masks[:, None]
        planes = [_blur(m, self.blur[0]), _blur(m, self.blur[1])]
        has_colour = self.use_colour and getattr(frame, "images", None) is not None
        if has_colour:
            img = frame.images
            col = img.to(dt).permute(0, 3, 1, 2)
            if img.dtype == torch.uint8:
                col = col / 255.0
            planes.append(col)
        else:
            planes.append(m.new_zeros(m.shape[0], 3, *m.shape[2:]))
        return FeatureObservation(torch.cat(planes, 1), sil.fg_pixels, sil.fg_valid,
                                  sil.view_valid, has_colour)

    def evidence(self, observation: FeatureObservation) -> bool:
        return bool(observation.view_valid.any())

    # ------------------------------------------------------------------ energy
    def features(self, poses, obs: FeatureObservation) -> tuple[torch.Tensor, torch.Tensor]:
        """Point features ``(P, C, N, 6)`` and pixel features ``(P, C, G, 3)``."""
        kin = poses.kinematics
        ep = poses.endpoints(self.body)  # (P, B, 2, 3)
        dt = ep.dtype
        P, B = ep.shape[:2]
        t, radial = _per_bone(self.pattern, B)
        t, radial = t.to(dt), radial.to(dt)
        Rb = kin.rotations[:, self.body.parent_index]
        n = torch.einsum("pbij,bkj->pbki", Rb, radial)
        a = ep[:, :, 0, None]
        pts = torch.addcmul(a, t[None, :, :, None], ep[:, :, 1, None] - a)
        pts = pts + self.body.radii.to(dt)[None, :, None, None] * n
        pts, n = pts.reshape(-1, 3), n.reshape(-1, 3)  # (M, 3), M = P N
        u, v, _, vis = self.rig.project_planar(pts)  # (C, M)
        C = u.shape[0]
        centres = self.rig.camera_centers().to(dt)
        facing = (centres @ n.T > (pts * n).sum(-1)) & vis
        facing = facing & obs.view_valid.to(facing.device)[:, None]
        planes = obs.planes.to(dt)
        if torch.is_grad_enabled() and (u.requires_grad or planes.requires_grad):
            vals = bilinear_lookup(planes, u, v)  # (C, 5, M), twice differentiable
        else:  # the same values (zero outside), faster
            H, W = planes.shape[-2:]
            g = torch.stack([(u + 0.5) / W * 2 - 1, (v + 0.5) / H * 2 - 1], -1)[:, None]
            vals = F.grid_sample(planes, g, mode="bilinear", padding_mode="zeros",
                                 align_corners=False)[:, :, 0]
        f = facing.to(dt)
        cnt = f.sum(0)  # (M,)
        col = vals[:, 2:]  # (C, 3, M)
        mean = (col * f[:, None]).sum(0) / cnt.clamp_min(1)  # (3, M)
        dev = ((col - mean) ** 2).sum(1) * f  # (C, M)
        seen = (cnt / C).expand(C, -1)
        pf = torch.stack([vals[:, 0], vals[:, 1], f, vis.to(dt), dev, seen], -1)  # (C, M, 6)
        N = pts.shape[0] // P
        pf = pf.view(C, P, N, -1).transpose(0, 1)
        st = _stadiums(ep, self.body.radii, self.rig)
        margin = _coverage_margin(obs.fg_pixels, st, smooth=True)  # (C, G, P)
        margin = margin.permute(2, 0, 1)
        xf = torch.stack([torch.sigmoid(margin), torch.sigmoid(margin / 4),
                          torch.tanh(margin / 20)], -1)
        return pf, xf

    def energy(self, poses, observation: FeatureObservation) -> torch.Tensor:
        pf, xf = self.features(poses, observation)
        bone = self.pattern["bone"].to(pf.device)
        return self.net(pf, bone, xf, observation.fg_valid, observation.view_valid)

    def extra_repr(self) -> str:
        return (f"hidden={self.hidden}, depth={self.depth}, points={self.axial}x{self.around}, "
                f"fg_samples={self.fg_samples}, use_colour={self.use_colour}, "
                f"weights={self.weights_path}")
