"""Robust reprojection energy of a detector's keypoints (OpenPose, RTMPose, ...).

The observation of a frame is ``joints2d (C, K, 3)`` = (u, v, confidence) per camera and
keypoint of the detector's format, in the column order ``keypoint_names`` (the runtime
dependency filled from the sequence's ``joint_names``; confidence 0 = missed). A
:class:`~torchmocap.skeleton.KeypointMap` places the ``K'`` mapped keypoints on the skeleton
(joint + offset in a bone frame, :func:`~torchmocap.skeleton.keypoint_positions`); they are
projected by the rig (lens distortion included) and scored with the robust energy of
:mod:`torchmocap.likelihoods.joints2d`::

    V(theta) = N * (sum_ck w_ck rho(z_ck)) / (sum_ck w_ck),   z_ck = |pi_c(x_k) - u_ck|^2 / s_c^2

with ``w_ck`` the confidences (0 below ``min_confidence``, and for every keypoint of a view the
frame marks dropped), ``N`` the number of valid detections (``reduction="sum"``) and ``s_c`` the
robust scale of camera ``c`` (one number, or one per camera). A frame without any valid
detection behaves as in :class:`~torchmocap.likelihoods.Joints2DLikelihood` (``on_empty``), and
:meth:`KeypointLikelihood.evidence` reports it.

The offsets ``(K', 3)`` and the log-scales ``(C,)`` are ``nn.Parameter``\\ s, frozen by default
(``learn_offsets`` / ``learn_scale`` make them trainable). The energy omits the
``log s_c`` normalisation of the density, so an objective training the scales must not reward
a large scale by itself (a normalised likelihood or a ranking loss).

Shapes: ``P`` poses, ``C`` cameras, ``K`` keypoints of the format, ``K'`` mapped keypoints.

Example:
    >>> from torchmocap.skeleton import human31, load_keypoint_map, keypoint_positions
    >>> from torchmocap.cameras import make_ring_rig
    >>> from torchmocap.data import Frame
    >>> from torchmocap.likelihoods import FrameEnergy
    >>> sk, rig = human31(), make_ring_rig(2).float()
    >>> kin = sk(sk.zero_pose((1,)))
    >>> x = keypoint_positions(kin.positions, kin.rotations, load_keypoint_map("body_25b"))
    >>> pix = rig.project(x[0])[0]                                       # (C, 25, 2)
    >>> frame = Frame(0, 0.0, joints2d=torch.cat([pix, torch.ones(2, 25, 1)], -1))
    >>> term = KeypointLikelihood(rig, sk, keypoint_map="body_25b")
    >>> V = FrameEnergy(term, term.prepare(frame), sk)
    >>> V(sk.zero_pose((3,))).shape
    torch.Size([3])
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import nn

from torchmocap.likelihoods.base import Likelihood, Poses
from torchmocap.likelihoods.joints2d import (
    EmptyEvidenceError,
    Joints2DObservation,
    check_detection_settings,
    joints2d_energy,
)
from torchmocap.skeleton.keypoints import KeypointMap, keypoint_positions, load_keypoint_map

__all__ = ["KeypointLikelihood"]


def _check_scales(scale_px, C: int) -> list[float]:
    vals = scale_px if isinstance(scale_px, (list, tuple)) else [scale_px]
    ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
             and v > 0 for v in vals)
    if not ok or len(vals) not in (1, C):
        raise ValueError(f"scale_px: expected a finite number > 0 or a list of {C} (one per "
                         f"camera), got {scale_px!r}")
    return [float(v) for v in vals] * (C if len(vals) == 1 else 1)


class KeypointLikelihood(Likelihood):
    """Robust, confidence-weighted reprojection energy of mapped detector keypoints.

    Args:
        rig: the :class:`~torchmocap.cameras.CameraRig` of the detections (runtime dependency).
        skeleton: the tracking skeleton (runtime dependency; the map is bound to its joints;
            default: the map's preset).
        keypoint_names: the ``K`` column names of the detections (runtime dependency; default:
            the format's own order, ``keypoint_map.format_keypoints``).
        keypoint_map: a built-in format name (``body_25b``, ``body_25``, ``coco_17``,
            ``halpe_26``), a map YAML path, or a :class:`~torchmocap.skeleton.KeypointMap`
            (runtime dependency: the subject's map fitted to the recording, with its offsets
            scaled to the body, else the detections' format).
        scale_px: robust scale ``s`` in pixels at the detections' image scale: one number or a
            list with one per camera.
        robust: ``"cauchy"`` (default), ``"geman_mcclure"``, ``"huber"`` or ``"gaussian"``.
        min_confidence: detections below this confidence are skipped.
        reduction: ``"sum"`` (``N`` times the weighted mean cost; default) or ``"mean"``.
        on_empty: ``"raise"`` (:class:`~torchmocap.likelihoods.EmptyEvidenceError` from
            :meth:`prepare`) or ``"uninformative"`` (a constant, non-zero energy).
        learn_offsets: make the keypoint offsets trainable.
        learn_scale: make the per-camera log-scales trainable.
        surface_keypoints: once a body fit has set the subject's Anny phenotype on ``body``
            (:class:`~torchmocap.filters.AnnyBodyFit`), place the keypoints a detector marks on
            the skin (nose, eyes, ears, head top, heels, toe tips) on the fitted body's surface
            (:mod:`torchmocap.body.surface_keypoints`); the others, and every keypoint before
            the fit, keep the map's offsets.
        surface_anchor: ``"map"`` (default: the surface shapes each group of keypoints on one
            joint, the map places it; measured better on a real recording than ``"joint"``)
            or ``"joint"`` (the points where the body puts them):
            :func:`~torchmocap.body.surface_keypoints.surface_keypoint_offsets`.
        body: the runtime :class:`~torchmocap.body.CapsuleBody` (read by
            ``surface_keypoints`` only).
        cache_dir: the Anny cache folder (``surface_keypoints``).

    Raises:
        KeypointMapError: a mapped keypoint is not among ``keypoint_names`` (names it), or the
            map's joints are not the skeleton's.
        ValueError: other bad settings (the message names the argument).
    """

    requires = ("joints2d",)

    def __init__(self, rig, skeleton=None, keypoint_names: Sequence[str] | None = None,
                 keypoint_map: str | Path | KeypointMap = "body_25b",
                 scale_px: float | Sequence[float] = 8.0, robust: str = "cauchy",
                 min_confidence: float = 0.0, reduction: str = "sum", on_empty: str = "raise",
                 learn_offsets: bool = False, learn_scale: bool = False,
                 surface_keypoints: bool = False, surface_anchor: str = "map", body=None,
                 cache_dir: str | None = None) -> None:
        super().__init__()
        if not isinstance(surface_keypoints, bool):
            raise ValueError(f"surface_keypoints: expected true or false, got "
                             f"{surface_keypoints!r}")
        if surface_keypoints and learn_offsets:
            raise ValueError("surface_keypoints: the offsets come from the fitted body; they "
                             "cannot also be learned (learn_offsets=true)")
        if surface_anchor not in ("joint", "map"):
            raise ValueError(f"surface_anchor: expected 'joint' or 'map', got "
                             f"{surface_anchor!r}")
        if surface_keypoints and body is None:
            raise ValueError("surface_keypoints: needs the runtime body (the tracker's "
                             "CapsuleBody, fitted by body_fit=anny)")
        check_detection_settings(type(self).__name__, rig, robust, reduction, on_empty,
                                 min_confidence)
        scales = _check_scales(scale_px, rig.num_cameras)
        self.kmap = load_keypoint_map(keypoint_map, skeleton)
        self.keypoint_names = (list(self.kmap.format_keypoints) if keypoint_names is None
                               else [str(n) for n in keypoint_names])
        self.register_buffer("columns", self.kmap.columns(self.keypoint_names), persistent=False)
        self.rig = rig
        self.skeleton = skeleton
        self.robust = robust
        self.reduction = reduction
        self.on_empty = on_empty
        self.min_confidence = float(min_confidence)
        self.offsets = nn.Parameter(self.kmap.offsets.float(), requires_grad=bool(learn_offsets))
        self.log_scale_px = nn.Parameter(torch.tensor(scales).log(),
                                         requires_grad=bool(learn_scale))
        self.surface_keypoints = surface_keypoints
        self.surface_anchor = surface_anchor
        self.body = body if surface_keypoints else None
        self.cache_dir = cache_dir
        self._parametric = None
        self._surface_phenotype = None  # the phenotype the offsets were read off
        #: the keypoints placed on the fitted body's surface (empty before a body fit)
        self.surface_placed: list[str] = []

    @property
    def scale_px(self) -> torch.Tensor:
        """``(C,)`` robust scales in pixels."""
        return self.log_scale_px.exp()

    # ------------------------------------------------------------------ observation
    def prepare(self, frame) -> Joints2DObservation:
        """The frame's detections of the mapped keypoints, weights and evidence counts
        (``observation.joints`` indexes the ``K'`` mapped keypoints)."""
        j2d = getattr(frame, "joints2d", frame)
        where = f"frame {getattr(frame, 'index', '?')}"
        if j2d is None:
            raise ValueError(f"joints2d: {where} has no 2D keypoint detections")
        C, K = self.rig.num_cameras, len(self.keypoint_names)
        if not isinstance(j2d, torch.Tensor) or j2d.shape != (C, K, 3):
            shape = tuple(j2d.shape) if isinstance(j2d, torch.Tensor) else type(j2d).__name__
            raise ValueError(f"joints2d: expected shape ({C}, {K}, 3) (cameras, keypoints "
                             f"{self.keypoint_names[:3]}..., (u, v, confidence)), got {shape}")
        sel = j2d.index_select(1, self.columns.to(j2d.device))
        uv, conf = sel[..., :2], sel[..., 2]
        finite = torch.isfinite(uv).all(-1) & torch.isfinite(conf)
        if bool((finite & (conf < 0)).any()):
            raise ValueError("joints2d: confidences must be >= 0")
        keep = finite & (conf > 0) & (conf >= self.min_confidence)
        dropped = getattr(frame, "view_dropped", None)
        if dropped is not None:
            keep = keep & ~dropped.to(device=keep.device, dtype=torch.bool)[:, None]
        w = torch.where(keep, conf, torch.zeros_like(conf)).clamp(max=1.0)
        uv = torch.where(finite[..., None], uv, torch.zeros_like(uv))
        idx = torch.arange(self.kmap.num_keypoints, device=j2d.device)
        n = int((w > 0).sum())
        if n == 0:
            if self.on_empty == "raise":
                raise EmptyEvidenceError(
                    f"joints2d: {where} has no valid keypoint detection (every confidence is 0, "
                    f"below min_confidence={self.min_confidence}, or in a dropped view); a "
                    "frame without evidence cannot be scored (on_empty='uninformative' gives it "
                    "a constant energy)")
            return Joints2DObservation(uv, w, idx, 0, 0.0, empty=True)
        return Joints2DObservation(uv, w, idx, n, float(w.double().sum()))

    def evidence(self, observation: Joints2DObservation) -> bool:
        """False for a frame without any valid detection (``on_empty="uninformative"``)."""
        return not observation.empty

    # ------------------------------------------------------------------ energy
    def _sync_surface(self) -> None:
        """Read the offsets of the surface keypoints off the body's fitted phenotype (once per
        fit)."""
        phen = getattr(self.body, "surface_phenotype", None)
        if phen is None or phen is self._surface_phenotype:
            return
        from torchmocap.body import ParametricBody
        from torchmocap.body.surface_keypoints import surface_keypoint_offsets

        sk = self.body.skeleton
        if self._parametric is None:
            self._parametric = ParametricBody(sk, cache_dir=self.cache_dir).to(
                sk.offsets.device)
        off, placed = surface_keypoint_offsets(self.kmap, self._parametric, phen, sk.offsets,
                                               self.surface_anchor)
        with torch.no_grad():
            self.offsets.copy_(off.to(self.offsets))
        self._surface_phenotype, self.surface_placed = phen, placed

    def keypoints(self, poses: Poses) -> torch.Tensor:
        """``(P, K', 3)`` world positions of the mapped keypoints of ``poses``."""
        if self.surface_keypoints:
            self._sync_surface()
        kin = poses.kinematics
        return keypoint_positions(kin.positions, kin.rotations, self.kmap, self.offsets)

    def fitted_map(self) -> KeypointMap:
        """The keypoint map with this term's current offsets (the model points it scores:
        a held-out view is scored with the same points)."""
        if self.surface_keypoints:
            self._sync_surface()
        return dataclasses.replace(self.kmap, offsets=self.offsets.detach().to(
            device="cpu", dtype=torch.float64).clone())

    def energy(self, poses: Poses, observation: Joints2DObservation) -> torch.Tensor:
        x = self.keypoints(poses)
        return joints2d_energy(x, observation, self.rig, self.scale_px.to(x), self.robust,
                               self.reduction)

    def extra_repr(self) -> str:
        return (f"format={self.kmap.format!r}, keypoints={self.kmap.num_keypoints}, "
                f"scale_px={[round(float(s), 3) for s in self.scale_px]}, "
                f"robust={self.robust!r}, reduction={self.reduction!r}, "
                f"on_empty={self.on_empty!r}")
