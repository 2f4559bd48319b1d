"""Appearance term V_app (Pons-Moll et al. 2010, eq. 17): colour consistency of the visible surface.

A fixed pattern of body-fixed points (``axial x around`` per capsule, moving rigidly with the
bone) is projected into every view; each point's colour is read where it faces the camera and
lies inside the image. A correct pose sees the same surface point with the same colour in all
views that see it; a wrong pose mixes body and background. ``V_app`` is the mean (over points
seen by at least two views) of the across-view colour variance, in units of the full colour
range squared (so in [0, 0.25]); a pose none of whose points is seen by two views gets 0.25.
Self-occlusion by other body parts (``occlusion``): with ``"none"`` a point hidden behind an arm
in one view reads the arm's colour there, so even the true pose pays a variance and poses that
hide fewer points are favoured. ``"rays"`` counts a point as unseen in a view whose line of sight
to it passes through another capsule of the same pose (:func:`~torchmocap.body.
rays_blocked_by_capsules`; exact for the capsule body, but ``O(P N B C)``: ~18x the term's own
cost at 200 particles). ``"outlier"`` drops, for every point seen by three or more views, the
one view whose colour is farthest from the mean of the others (a hidden point reads a different
part in the view that does not see it; cheap, and a wrong pose keeps at least two disagreeing
views).
Shapes: ``P`` particles, ``C`` views, ``B`` capsules, ``N`` surface points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchmocap.body.capsules import rays_blocked_by_capsules
from torchmocap.compilation import CompiledFunction
from torchmocap.likelihoods.base import Likelihood

__all__ = [
    "OCCLUSION",
    "AppearanceLikelihood",
    "ColourObservation",
    "appearance_energy",
    "body_surface_pattern",
    "prepare_images",
]

#: self-occlusion handling of :func:`appearance_energy` (see the module docstring)
OCCLUSION = ("none", "rays", "outlier")


def body_surface_pattern(body, axial: int = 4, around: int = 6) -> dict[str, torch.Tensor]:
    """Body-fixed surface pattern of a :class:`~torchmocap.body.CapsuleBody`.

    ``axial x around`` points per capsule, bone-major (capsule ``b`` owns points
    ``b*k .. b*k + k - 1`` with ``k = axial * around``). Returns tensors ``bone (N,)`` (capsule
    index), ``t (N,)`` position along the axis, ``radial (N, 3)`` unit direction in the rest
    frame of the bone's parent joint.
    """
    if axial < 1 or around < 1:
        raise ValueError(f"axial, around: expected integers >= 1, got {axial}, {around}")
    sk = body.skeleton
    rest = sk(sk.zero_pose(dtype=torch.float64)).positions
    a = rest[body.parent_index]
    b = rest[body.child_index]
    axis = torch.nn.functional.normalize(b - a, dim=-1)
    helper = torch.where((axis[:, :1].abs() < 0.9), torch.tensor([1.0, 0, 0], dtype=axis.dtype),
                         torch.tensor([0, 1.0, 0], dtype=axis.dtype))
    e1 = torch.nn.functional.normalize(torch.cross(axis, helper, dim=-1), dim=-1)
    e2 = torch.cross(axis, e1, dim=-1)
    t = (torch.arange(axial, dtype=torch.float64) + 0.5) / axial
    phi = torch.arange(around, dtype=torch.float64) * (2 * math.pi / around)
    B = a.shape[0]
    radial = (torch.cos(phi)[None, :, None] * e1[:, None] + torch.sin(phi)[None, :, None]
              * e2[:, None])  # (B, around, 3)
    bone = torch.arange(B).repeat_interleave(axial * around)
    tt = t.repeat_interleave(around).repeat(B)
    rad = radial[:, None].expand(B, axial, around, 3).reshape(-1, 3)
    return {"bone": bone, "t": tt, "radial": rad}


def _per_bone(pattern: dict, num_bones: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``t (B, k)`` and ``radial (B, k, 3)`` of a bone-major pattern (typed error otherwise)."""
    bone = pattern["bone"]
    n = bone.shape[0]
    k = n // max(num_bones, 1)
    if k * num_bones != n or not torch.equal(
            bone, torch.arange(num_bones, device=bone.device).repeat_interleave(k)):
        raise ValueError(f"pattern: expected a bone-major layout with the same number of points "
                         f"on each of the {num_bones} capsules (see body_surface_pattern)")
    return pattern["t"].reshape(num_bones, k), pattern["radial"].reshape(num_bones, k, 3)


@dataclass
class ColourObservation:
    """Colour images prepared once per frame for :func:`appearance_energy`.

    Attributes:
        planes: ``(3, C*H*W + 1)`` channel planes in [0, 1]; the extra last pixel is 0 and is
            where unseen surface points read from.
        shape: ``(C, H, W)``.
    """

    planes: torch.Tensor
    shape: tuple[int, int, int]


def prepare_images(images, dtype: torch.dtype = torch.float32) -> ColourObservation:
    """Colour ``images (C, H, W, 3)`` (uint8 or [0, 1] floats) as a :class:`ColourObservation`.

    Do it once per frame; :func:`appearance_energy` accepts either form.
    """
    if isinstance(images, ColourObservation):
        return images if images.planes.dtype == dtype else ColourObservation(
            images.planes.to(dtype), images.shape)
    if not isinstance(images, torch.Tensor) or images.dim() != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected shape (C, H, W, 3), got "
                         f"{tuple(getattr(images, 'shape', ()))}")
    C, H, W, _ = images.shape
    planes = torch.zeros(3, C * H * W + 1, dtype=dtype, device=images.device)
    planes[:, :-1] = images.reshape(-1, 3).T
    if images.dtype == torch.uint8:
        planes /= 255.0
    return ColourObservation(planes, (C, H, W))


def _first_max(x: torch.Tensor) -> torch.Tensor:
    """``(C, M)`` bool: the first maximum of every column (``arange(C)[:, None] ==
    x.argmax(0)``, ties to the lowest row) — a reduction over the short leading dim that
    ``argmax(0)`` makes ~20x slower on the CPU than this row-by-row mask."""
    m = x.amax(0)
    out = torch.empty(x.shape, dtype=torch.bool, device=x.device)
    free = torch.ones_like(m, dtype=torch.bool)
    for c in range(x.shape[0]):
        torch.logical_and(x[c] == m, free, out=out[c])
        free &= ~out[c]
    return out


def appearance_energy(kin, body, pattern: dict, rig, images,
                      view_valid: torch.Tensor | None = None,
                      endpoints: torch.Tensor | None = None,
                      occlusion: str = "none", min_facing: float = 0.0) -> torch.Tensor:
    """``V_app (P,)`` of poses ``kin`` against colour ``images (C, H, W, 3)`` (uint8 or [0, 1]),
    or their :func:`prepare_images` form (no per-call conversion). ``endpoints`` may pass
    ``body.endpoints(kin)`` when the caller already has them; ``occlusion``: ``"none"``,
    ``"rays"`` or ``"outlier"`` (see the module docstring)."""
    dtype = kin.positions.dtype
    ep = body.endpoints(kin) if endpoints is None else endpoints  # (P, B, 2, 3)
    t, radial = _per_bone(pattern, ep.shape[1])
    return _appearance_energy(kin, body, t, radial, rig, prepare_images(images, dtype),
                              view_valid, ep, occlusion, min_facing)


def _appearance_energy(kin, body, t: torch.Tensor, radial: torch.Tensor, rig,
                       obs: ColourObservation, view_valid: torch.Tensor | None,
                       ep: torch.Tensor, occlusion: str, min_facing: float,
                       distorted: bool | None = None) -> torch.Tensor:
    """:func:`appearance_energy` on checked inputs: the pattern as ``t (B, k)``,
    ``radial (B, k, 3)``, the images prepared, the endpoints ``ep (P, B, 2, 3)`` given;
    ``distorted``: the rig's ``has_distortion`` when known (then no host read of tensor values
    is left, except with ``occlusion="rays"``, and the function compiles into one graph)."""
    dtype = kin.positions.dtype
    P, B = ep.shape[:2]
    t, radial = t.to(ep.device, dtype), radial.to(ep.device, dtype)
    Rb = kin.rotations[:, body.parent_index]  # (P, B, 3, 3)
    n = torch.einsum("pbij,bkj->pbki", Rb, radial)  # (P, B, k, 3) surface normals
    a = ep[:, :, 0, None]
    pts = torch.addcmul(a, t[None, :, :, None], ep[:, :, 1, None] - a)
    pts = pts.add_(body.radii.to(dtype)[None, :, None, None] * n)
    if occlusion not in OCCLUSION:
        raise ValueError(f"occlusion: expected one of {OCCLUSION}, got {occlusion!r}")
    hidden = None
    if occlusion == "rays":
        own = torch.arange(B, device=pts.device).repeat_interleave(t.shape[1])
        hidden = rays_blocked_by_capsules(rig.camera_centers().to(dtype),
                                          pts.reshape(P, -1, 3), ep,
                                          body.radii.to(dtype), own).reshape(-1, P * own.numel())
    pts, n = pts.reshape(-1, 3), n.reshape(-1, 3)  # (M, 3) with M = P * N
    # view-major planes (C, M): the reductions over views below run over a leading dim
    u, v, _, vis = rig.project_planar(pts, distorted=distorted)
    centres = rig.camera_centers().to(dtype)  # (C, 3)
    # (c - x) . n > cos_min |c - x|: the point faces the camera (by more than grazing)
    facing = centres @ n.T - (pts * n).sum(-1)  # (C, M)
    if min_facing > 0:
        dist = torch.cdist(centres, pts)  # (C, M)
        ok = vis & (facing > min_facing * dist)
    else:
        ok = vis & (facing > 0)
    if hidden is not None:
        ok = ok & ~hidden
    if view_valid is not None:
        ok = ok & view_valid.to(ok.device)[:, None]
    C, H, W = obs.shape
    # flat pixel index computed in floats: exact below 2^24 pixels in float32
    it = dtype if C * H * W < 2**24 or dtype == torch.float64 else torch.float64
    u, v = u.to(it), v.to(it)
    base = (torch.arange(C, device=u.device, dtype=it) * (H * W))[:, None]
    # pixel x covers [x - 0.5, x + 0.5): the index is floor(u + 0.5)
    x = (u + 0.5).clamp_(0, W - 1).floor_().add_(base)
    idx = torch.addcmul(x, (v + 0.5).clamp_(0, H - 1).floor_(),
                        torch.full((), W, dtype=it, device=u.device))
    idx = torch.where(ok, idx.long(), C * H * W)  # unseen -> the 0 pixel
    cols = obs.planes.index_select(1, idx.reshape(-1)).reshape(3, C, -1)  # (3, C, M)
    if occlusion == "outlier":  # drop each point's most discrepant view when >= 3 see it
        k = ok.sum(0)  # (M,)
        others = (cols.sum(1, keepdim=True) - cols) / (k - 1).clamp_min(1).to(dtype)
        dev = torch.where(ok, (cols - others).square().sum(0), -1.0)  # (C, M)
        drop = (k >= 3) & _first_max(dev)
        ok = ok & ~drop
        cols = cols * ok.to(dtype)
    cnt = ok.sum(0).to(dtype)  # (M,)
    s1 = cols.sum(1)  # (3, M)
    s2 = (cols * cols).sum((0, 1))  # (M,)
    inv = 1.0 / cnt.clamp_min(1)
    # across-view variance per point, averaged over the channels: E|c|^2 - |E c|^2
    var = ((s2 - (s1 * s1).sum(0) * inv) * inv / 3).clamp_min_(0).reshape(P, -1)
    seen = (cnt >= 2).to(dtype).reshape(P, -1)
    n_seen = seen.sum(-1)
    v = (var * seen).sum(-1) / n_seen.clamp_min(1)
    # a pose with no surface point seen by two views (out of the images) has no colour
    # evidence: it gets the largest variance (0.25), not a perfect 0
    return torch.where(n_seen > 0, v, torch.full_like(v, 0.25))


class AppearanceLikelihood(Likelihood):
    """Appearance energy ``V_app`` (eq. 17): across-view colour variance of a body-fixed
    surface pattern.

    Args:
        body: the :class:`~torchmocap.body.CapsuleBody` of the subject.
        rig: the :class:`~torchmocap.cameras.CameraRig` of the colour images.
        axial, around: surface points per capsule along and around its axis.
        occlusion: self-occlusion handling, ``"none"``, ``"rays"`` or ``"outlier"`` (see the
            module docstring).
        min_facing: a point counts in a view only where the cosine between its normal and the
            line of sight exceeds this (in [0, 1); 0: every facing view). Seen at a grazing
            angle a point's pixel lies on its limb's outline and reads the background or the
            part behind, so even the true pose pays there (opt-in: config key
            ``+likelihood.terms.appearance.min_facing=0.5``).
        compile: run the energy through ``torch.compile`` (:mod:`torchmocap.compilation`:
            the first call compiles; not bit-identical to the eager energy, falls back to it
            when compiling fails).

    ``requires = ("images",)``; ``prepare(frame)`` converts the colour images once per frame
    (views flagged in ``frame.view_dropped`` are excluded).
    """

    requires = ("images",)

    def __init__(self, body, rig, axial: int = 3, around: int = 4, occlusion: str = "none",
                 min_facing: float = 0.0, compile: bool = False):
        super().__init__()
        if not isinstance(compile, bool):
            raise ValueError(f"compile: expected true or false, got {compile!r}")
        self._energy = CompiledFunction(_appearance_energy, "terms.appearance.compile", compile)
        if isinstance(min_facing, bool) or not isinstance(min_facing, (int, float)) \
                or not 0 <= min_facing < 1:
            raise ValueError(f"min_facing: expected a cosine in [0, 1), got {min_facing!r}")
        self.min_facing = float(min_facing)
        if occlusion not in OCCLUSION:
            raise ValueError(f"occlusion: expected one of {OCCLUSION}, got {occlusion!r}")
        self.occlusion = occlusion
        self.body = body
        self.rig = rig
        self.axial, self.around = int(axial), int(around)
        self.pattern = body_surface_pattern(body, self.axial, self.around)
        self._t, self._radial = _per_bone(self.pattern, body.num_bones)

    def prepare(self, frame) -> tuple[ColourObservation, torch.Tensor | None]:
        view_valid = None
        if getattr(frame, "view_dropped", None) is not None:
            view_valid = ~frame.view_dropped.bool()
        return prepare_images(frame.images, self.body.radii.dtype), view_valid

    def evidence(self, observation) -> bool:
        _, view_valid = observation
        return view_valid is None or int(view_valid.sum()) >= 2

    def energy(self, poses, observation) -> torch.Tensor:
        colours, view_valid = observation
        return self._energy(poses.kinematics, self.body, self._t, self._radial, self.rig,
                            colours, view_valid, poses.endpoints(self.body), self.occlusion,
                            self.min_facing, self.rig.has_distortion)

    def extra_repr(self) -> str:
        return (f"axial={self.axial}, around={self.around}, occlusion={self.occlusion!r}, "
                f"min_facing={self.min_facing}" + (", compile=True" if self._energy.enabled
                                                   else ""))
