"""A detector's keypoints with the hand-set parts of the likelihood made trainable.

:class:`LearnedKeypointLikelihood` is :class:`~torchmocap.likelihoods.KeypointLikelihood` with

- the keypoint offsets ``o_k`` (in their bone frames) trainable, starting at the map's;
- a robust scale per camera and keypoint ``s_ck = s_c exp(l_k)`` (``s_c`` the per-camera scale,
  ``l_k`` a log-factor per keypoint, 0 untrained);
- a pixel bias per camera ``b_c`` (a systematic shift of that view's detections from the
  projected keypoints — a detector's habit or a small calibration error — stored as a fraction
  of the image's width and height, so it holds at any image scale; 0 untrained);
- the detector's confidence ``c`` mapped to the detection's weight by a calibration ``g(c)``
  that is monotone by construction (:func:`monotone_calibration`): piecewise linear through
  ``B + 1`` knots ``c_i = i / B`` with values ``v_0 = 0``,
  ``v_i = sum_{j < i} softplus(a_j) / (sum_{j < B} softplus(a_j) + softplus(a_B))`` — positive
  increments, so ``g`` increases for any parameters and stays in ``[0, 1)``.

The energy is that of the hand-set term with ``w_ck = g(c_ck)``, ``s_ck`` and ``b_c``::

    V(theta) = N * (sum_ck w_ck rho(z_ck)) / (sum_ck w_ck),
    z_ck = |pi_c(x_k) + b_c - u_ck|^2 / s_ck^2

Untrained (``weights=None``), ``g(c) = c / (1 + 1e-6)``, ``l_k = 0`` and ``b_c = 0``: the
weights differ from the confidences by one common factor, which the normalisation ``N / sum w``
cancels, so the energy is the hand-set term's (to rounding).

Weights files (:mod:`torchmocap.likelihoods.learned`'s format, written atomically) hold the
offsets as changes from the map's (metres; a subject fit scales the map, the change is kept),
the per-camera log-factors and pixel biases by camera name, the per-keypoint log-factors and the
calibration's parameters, with ``config`` (the map's format, keypoints, joints and frames, the
robust function, the number of knots) checked on load: another map or setting is refused
naming each difference; the camera parameters apply by camera name (a held-out run's subset
takes its cameras'), and a camera the file does not know keeps the untrained values, with a
warning naming it. Training: :mod:`torchmocap.learning.keypoints`.

Shapes: ``P`` poses, ``C`` cameras, ``K'`` mapped keypoints, ``B`` calibration segments.

Example:
    >>> from torchmocap.cameras import make_ring_rig
    >>> from torchmocap.skeleton import human31
    >>> term = LearnedKeypointLikelihood(make_ring_rig(2).float(), human31())
    >>> term.calibrated(torch.tensor([0.0, 0.5, 1.0])).round(decimals=4)
    tensor([0.0000, 0.5000, 1.0000])
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from torchmocap.likelihoods.base import Poses
from torchmocap.likelihoods.joints2d import (
    Joints2DObservation,
    joints2d_energy,
    weighted_robust_sum,
)
from torchmocap.likelihoods.keypoints import KeypointLikelihood
from torchmocap.likelihoods.learned import (
    ArchitectureMismatchError,
    WeightsError,
    _resolve,
    compare_configs,
    read_weights,
    write_weights,
)
from torchmocap.skeleton.keypoints import KeypointMap

__all__ = ["LearnedKeypointLikelihood", "expected_pixels", "identity_calibration",
           "keypoint_scales", "monotone_calibration"]

_TAIL = 1e-6  # softplus of the last calibration parameter, untrained (g(1) = 1 / (1 + _TAIL))


def identity_calibration(knots: int) -> torch.Tensor:
    """``(B + 1,)`` float64 calibration parameters of ``g(c) = c / (1 + 1e-6)`` (untrained)."""
    inc = math.log(math.expm1(1.0 / knots))
    return torch.tensor([inc] * knots + [math.log(math.expm1(_TAIL))], dtype=torch.float64)


def monotone_calibration(conf: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
    """The weight ``g(c)`` of confidences ``conf (*)`` (module docstring): monotone
    non-decreasing in ``c`` for any ``params (B + 1,)``, ``g(0) = 0``, values in ``[0, 1)``;
    confidences outside ``[0, 1]`` are clamped. Differentiable in ``params``."""
    B = params.shape[-1] - 1
    inc = F.softplus(params[:B])
    v = torch.cat([inc.new_zeros(1), inc.cumsum(0)]) / (inc.sum() + F.softplus(params[B]))
    x = conf.to(v).clamp(0.0, 1.0) * B
    i = x.detach().floor().clamp(max=B - 1).long()
    return v[i] + (x - i.to(x)) * (v[i + 1] - v[i])


def keypoint_scales(log_scale_px: torch.Tensor, log_keypoint_scale: torch.Tensor
                    ) -> torch.Tensor:
    """``(C, K')`` robust scales ``s_ck = exp(log s_c + l_k)`` of per-camera log-scales
    ``(C,)`` and per-keypoint log-factors ``(K',)``."""
    return (log_scale_px[:, None] + log_keypoint_scale[None]).exp()


def expected_pixels(rig, x: torch.Tensor, pixel_bias: torch.Tensor) -> torch.Tensor:
    """``(P, C, K', 2)`` pixels where the detections of keypoints ``x (P, K', 3)`` are
    expected: the rig's projection plus each camera's bias ``pixel_bias (C, 2)`` (fractions of
    the image's width and height)."""
    pix = rig.project(x)[0]
    return pix + (pixel_bias.to(pix) * rig.image_size.to(pix))[:, None]


class LearnedKeypointLikelihood(KeypointLikelihood):
    """The keypoint energy with trainable offsets, scales and confidence calibration.

    ``rig``, ``skeleton``, ``keypoint_names``, ``keypoint_map``, ``scale_px``, ``robust``,
    ``min_confidence``, ``reduction`` and ``on_empty`` are those of
    :class:`~torchmocap.likelihoods.KeypointLikelihood` (the map's offsets and ``scale_px`` are
    the starting point).

    Args:
        calibration_knots: ``B``, the calibration's segments on ``[0, 1]``.
        weights: a weights file (:meth:`save_weights`, ``torchmocap-train
            --config-name train_keypoints``), ``"bundled"`` (the parameters shipped for the
            bundled pose2sim_balancing recording) or None (untrained: the hand-set energy).
        learn: the parameters require gradients (training); a tracker does not need them.

    Raises:
        ValueError: bad settings (names the argument); FileNotFoundError, WeightsError,
            ArchitectureMismatchError: a weights file that is missing, not one, or for another
            map or setting.
    """

    bundled = "keypoints_pose2sim_balancing.pt"

    def __init__(self, rig, skeleton=None, keypoint_names: Sequence[str] | None = None,
                 keypoint_map: str | Path | KeypointMap = "body_25b",
                 scale_px: float | Sequence[float] = 8.0, robust: str = "cauchy",
                 min_confidence: float = 0.0, reduction: str = "sum", on_empty: str = "raise",
                 calibration_knots: int = 10, weights: str | os.PathLike | None = None,
                 learn: bool = False) -> None:
        super().__init__(rig, skeleton, keypoint_names, keypoint_map, scale_px, robust,
                         min_confidence, reduction, on_empty, learn_offsets=bool(learn),
                         learn_scale=bool(learn))
        if isinstance(calibration_knots, bool) or not isinstance(calibration_knots, int) \
                or not 1 <= calibration_knots <= 100:
            raise ValueError(f"calibration_knots: expected an integer in [1, 100], got "
                             f"{calibration_knots!r}")
        self.calibration_knots = calibration_knots
        self.camera_names = [str(n) for n in rig.names]
        self.register_buffer("base_offsets", self.offsets.detach().clone())
        self.register_buffer("base_log_scale", self.log_scale_px.detach().clone())
        self.log_keypoint_scale = nn.Parameter(torch.zeros(self.kmap.num_keypoints),
                                               requires_grad=bool(learn))
        self.calibration = nn.Parameter(identity_calibration(calibration_knots).float(),
                                        requires_grad=bool(learn))
        self.pixel_bias = nn.Parameter(torch.zeros(rig.num_cameras, 2), requires_grad=bool(learn))
        self.weights_path: str | None = None
        if weights is not None:
            self.load_weights(_resolve(weights, self.bundled))

    # ------------------------------------------------------------------ parameters
    def scales(self) -> torch.Tensor:
        """``(C, K')`` robust scales ``s_ck`` in pixels."""
        return keypoint_scales(self.log_scale_px, self.log_keypoint_scale)

    def project(self, x: torch.Tensor) -> torch.Tensor:
        """``(P, C, K', 2)`` pixels where the detections of keypoints ``x (P, K', 3)`` are
        expected (:func:`expected_pixels` with this term's biases)."""
        return expected_pixels(self.rig, x, self.pixel_bias)

    def calibrated(self, conf: torch.Tensor) -> torch.Tensor:
        """The weights ``g(conf)`` (:func:`monotone_calibration`), same shape."""
        return monotone_calibration(conf, self.calibration)

    @property
    def config(self) -> dict[str, Any]:
        """The settings a weights file must match (map format, keypoints, joints, frames, robust
        function, calibration knots)."""
        return {"format": self.kmap.format, "keypoints": list(self.kmap.names),
                "joints": list(self.kmap.joints), "frames": list(self.kmap.frames),
                "robust": self.robust, "calibration_knots": self.calibration_knots}

    # ------------------------------------------------------------------ energy
    def energy(self, poses: Poses, observation: Joints2DObservation) -> torch.Tensor:
        x = self.keypoints(poses)
        if observation.empty:
            return joints2d_energy(x, observation, self.rig, 1.0, self.robust, self.reduction)
        return self.pixel_energy(self.project(x), observation.uv, observation.weight)

    def pixel_energy(self, pix: torch.Tensor, uv: torch.Tensor, conf: torch.Tensor
                     ) -> torch.Tensor:
        """The energy of projected keypoints ``pix (P, C, K', 2)`` given detections
        ``uv (..., C, K', 2)`` and confidences ``conf (..., C, K')`` (0 = skipped), broadcast
        against ``pix`` (one frame's, or one per pose: a batch of frames); a pose without any
        valid detection gets 0. Returns ``(P,)``."""
        conf = conf.to(pix)
        valid = conf > 0
        w = torch.where(valid, self.calibrated(conf), torch.zeros_like(conf))
        W = w.sum((-1, -2))
        n = valid.sum((-1, -2)).to(pix) if self.reduction == "sum" else torch.ones_like(W)
        norm = torch.where(W > 0, n / W.clamp_min(torch.finfo(W.dtype).tiny), torch.zeros_like(W))
        return weighted_robust_sum(pix, uv, w, self.scales().to(pix), self.robust) * norm

    # ------------------------------------------------------------------ weights files
    def weights_payload(self) -> dict[str, Any]:
        """The ``term``, ``config``, ``cameras`` and ``state_dict`` entries of a weights file
        (offsets and per-camera scales as changes from the starting point)."""
        with torch.no_grad():
            state = {"offset_delta": (self.offsets - self.base_offsets).double().cpu(),
                     "log_camera_factor": (self.log_scale_px - self.base_log_scale)
                     .double().cpu(),
                     "pixel_bias": self.pixel_bias.double().cpu().clone(),
                     "log_keypoint_scale": self.log_keypoint_scale.double().cpu().clone(),
                     "calibration": self.calibration.double().cpu().clone()}
        return {"term": type(self).__name__, "config": self.config,
                "cameras": list(self.camera_names), "state_dict": state}

    def save_weights(self, path: str | os.PathLike, **extra: Any) -> Path:
        """Write the parameters (and ``extra`` entries, e.g. a training summary) atomically."""
        return write_weights(path, {**self.weights_payload(), **extra})

    def load_weights(self, path: str | os.PathLike) -> None:
        """Load a weights file after checking its term, config and cameras.

        Raises:
            WeightsError: another term's file or malformed parameters;
            ArchitectureMismatchError: another keypoint map or setting (names each).

        Warns:
            UserWarning: cameras of the rig the file has no parameters for (named; they
                keep the untrained values).
        """
        payload = read_weights(path)
        name = type(self).__name__
        if payload["term"] != name:
            raise WeightsError(f"weights: {path} holds a {payload['term']} term, not a {name}")
        diff = compare_configs(payload["config"], self.config)
        if diff:
            raise ArchitectureMismatchError(
                f"weights: {path} was trained with another keypoint map or settings than this "
                f"{name}: " + "; ".join(diff))
        cams = [str(c) for c in payload.get("cameras", [])]
        missing = [c for c in self.camera_names if c not in cams]
        if missing:
            warnings.warn(f"weights: {path} has no scale or bias for cameras {missing} (it was "
                          f"trained on {cams}); they keep the untrained values", stacklevel=2)
        st = payload["state_dict"]
        K, B = self.kmap.num_keypoints, self.calibration_knots
        shapes = {"offset_delta": (K, 3), "log_camera_factor": (len(cams),),
                  "pixel_bias": (len(cams), 2),
                  "log_keypoint_scale": (K,), "calibration": (B + 1,)}
        for k, shape in shapes.items():
            v = st.get(k)
            if not isinstance(v, torch.Tensor) or tuple(v.shape) != shape \
                    or not bool(torch.isfinite(v).all()):
                raise WeightsError(f"weights: {path}: state_dict.{k}: expected finite values of "
                                   f"shape {shape}")
        with torch.no_grad():
            self.offsets.copy_(self.base_offsets + st["offset_delta"].to(self.base_offsets))
            for i, c in enumerate(self.camera_names):
                if c in cams:
                    j = cams.index(c)
                    self.log_scale_px[i] = self.base_log_scale[i] + st["log_camera_factor"][j]
                    self.pixel_bias[i] = st["pixel_bias"][j]
            self.log_keypoint_scale.copy_(st["log_keypoint_scale"])
            self.calibration.copy_(st["calibration"])
        self.weights_path = str(path)

    def extra_repr(self) -> str:
        return super().extra_repr() + (f", calibration_knots={self.calibration_knots}, "
                                       f"weights={self.weights_path!r}")
