"""Self-supervised training of :class:`~torchmocap.likelihoods.LearnedKeypointLikelihood` on a
recording: no ground truth, only the detections of the training views and frames.

Alternating maximum likelihood (:func:`train_keypoint_term`):

1. **poses**: every training frame's pose minimises the term's own energy (the tracker's) in the
   training views with the current parameters — per-frame projected L-BFGS
   (:func:`~torchmocap.filters.optim.minimise_local`) within the skeleton's limits, the first
   time frame by frame from the sequence's first pose, each frame starting at the previous
   frame's fit (:func:`track_poses`), afterwards all frames at once from their last fit
   (:func:`fit_poses`);
2. **parameters**: under those poses, the offsets, the scales, the pixel biases and the
   confidence calibration minimise the negative log-likelihood of every training detection
   (:func:`detection_nll`) plus Gaussian priors, by L-BFGS (:func:`fit_parameters`; with
   ``joint`` the poses move with them).

The detection model behind step 2 reads the term's parts as a density: with probability
``g(c)`` (the calibration of the confidence ``c``) a detection is the keypoint's projection plus
a 2D Student-t error of scale ``s_ck`` (``p(r) = (1 + |r|^2 / s^2)^-2 / (pi s^2)``: the
Cauchy-type influence of the energy, normalised so that a large scale is not free), else an
outlier uniform over the image (area ``A``)::

    -log p(u | c) = -log( g(c) t(u - pi_c(x_k); s_ck) + (1 - g(c)) / A )

with ``pi_c`` the projection plus the camera's pixel bias; so the calibration is fitted as
the probability that a detection of that confidence is right —
monotone by construction — and the term weights detections by it. The priors keep the offsets
near the map's (a Gaussian of ``offset_prior_m`` per coordinate: the anatomical estimate) and
the per-keypoint scale factors near 1 (``scale_prior`` in log units; it also fixes the product
of camera and keypoint factors) and the cameras' pixel biases near 0 (``bias_prior``; it also
fixes the shift common to all views, which a translation of the body explains as well).

Everything is deterministic on one machine (no sampling), so a training run is reproducible.

Shapes: ``T`` frames, ``C`` cameras, ``K'`` mapped keypoints, ``D`` pose DoF.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch

from torchmocap.filters.optim.local import minimise_local
from torchmocap.likelihoods.base import Poses
from torchmocap.likelihoods.joints2d import EmptyEvidenceError
from torchmocap.likelihoods.keypoints_learned import (
    expected_pixels,
    keypoint_scales,
    monotone_calibration,
)
from torchmocap.skeleton.keypoints import keypoint_positions

__all__ = ["Detections", "KeypointTrainSettings", "detection_nll", "fit_parameters",
           "fit_poses", "stack_detections", "track_poses", "train_keypoint_term"]


@dataclass
class KeypointTrainSettings:
    """Settings of :func:`train_keypoint_term` (``training.*`` of ``train_keypoints.yaml``).

    Attributes:
        rounds: alternations of the parameter and pose steps.
        pose_iterations: L-BFGS iterations of each pose fit (per frame).
        parameter_iterations: L-BFGS iterations of each parameter fit.
        offset_prior_m: std (metres) of the Gaussian prior of each offset coordinate around the
            keypoint map's.
        scale_prior: std of the per-keypoint log scale factors around 0.
        bias_prior: std of each camera's pixel bias around 0, as a fraction of the image's
            width / height (0.01: 11 / 19 px on 1088x1920 images); 0 (default) keeps the
            biases as they are (measured on pose2sim_balancing: trained biases did not help the
            held-out view, experiments/learned_real).
        joint: the parameter step moves the poses too (one L-BFGS on both): faster along the
            directions where an offset and a joint angle explain the detections almost alike;
            False (default) keeps the poses of the last pose step (plain alternation; the
            better held-out scores on pose2sim_balancing).
    """

    rounds: int = 4
    pose_iterations: int = 30
    parameter_iterations: int = 50
    offset_prior_m: float = 0.02
    scale_prior: float = 0.5
    bias_prior: float = 0.0
    joint: bool = False

    def check(self) -> None:
        """Raises ValueError naming the first bad setting."""
        for k in ("rounds", "pose_iterations", "parameter_iterations"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"training.{k}: expected an integer >= 1, got {v!r}")
        for k in ("offset_prior_m", "scale_prior", "bias_prior"):
            v = getattr(self, k)
            low = 0 if k == "bias_prior" else None
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (
                    math.isfinite(v) and (v > 0 or v == low)):
                raise ValueError(f"training.{k}: expected a number > 0"
                                 f"{' (or 0)' if low == 0 else ''}, got {v!r}")
        if not isinstance(self.joint, bool):
            raise ValueError(f"training.joint: expected true or false, got {self.joint!r}")


@dataclass
class Detections:
    """A sequence's detections of the term's mapped keypoints, stacked over frames.

    Attributes:
        uv: ``(T, C, K', 2)`` pixels.
        conf: ``(T, C, K')`` confidences, 0 where skipped (missed, below the term's
            ``min_confidence``, a dropped view).
        area: image area in pixels² (the outlier density's support), the mean over cameras.
    """

    uv: torch.Tensor
    conf: torch.Tensor
    area: float

    def frames(self, start: int, stop: int | None = None) -> Detections:
        """The detections of frames ``start .. stop - 1``."""
        return Detections(self.uv[start:stop], self.conf[start:stop], self.area)

    @property
    def num_valid(self) -> int:
        """Detections with a positive confidence."""
        return int((self.conf > 0).sum())


def stack_detections(term, seq) -> Detections:
    """:class:`Detections` of ``seq`` as ``term`` prepares them (a frame without any valid
    detection contributes zeros)."""
    uv, conf = [], []
    C, K = term.rig.num_cameras, term.kmap.num_keypoints
    for t in range(seq.num_frames):
        try:
            obs = term.prepare(seq.frame(t))
        except EmptyEvidenceError:
            uv.append(torch.zeros(C, K, 2))
            conf.append(torch.zeros(C, K))
            continue
        uv.append(obs.uv.float())
        conf.append(obs.weight.float())
    size = term.rig.image_size.double()
    return Detections(torch.stack(uv), torch.stack(conf), float(size.prod(-1).mean()))


def _project(term, positions: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    return term.project(keypoint_positions(positions, rotations, term.kmap, term.offsets))


def _energy_fn(term, skeleton, det: Detections):
    def energy(theta: torch.Tensor) -> torch.Tensor:
        kin = Poses(theta, skeleton).kinematics
        return term.pixel_energy(_project(term, kin.positions, kin.rotations), det.uv,
                                 det.conf)
    return energy


def fit_poses(term, skeleton, det: Detections, theta: torch.Tensor, iterations: int
              ) -> torch.Tensor:
    """Every frame's pose minimising the term's energy from ``theta (T, D)`` (independent
    per-frame L-BFGS within the skeleton's limits): ``(T, D)``."""
    lo, hi = skeleton.lower.to(theta), skeleton.upper.to(theta)
    res = minimise_local(_energy_fn(term, skeleton, det), theta.detach(), method="lbfgs",
                         iterations=iterations, lower=lo, upper=hi)
    return res.x.detach()


def track_poses(term, skeleton, det: Detections, theta0: torch.Tensor, iterations: int
                ) -> torch.Tensor:
    """Frame by frame: frame 0 from ``theta0 (D,)``, each later frame from the previous fit
    (:func:`fit_poses` of one frame): ``(T, D)``."""
    out, prev = [], theta0.detach()[None]
    for t in range(det.uv.shape[0]):
        one = Detections(det.uv[t:t + 1], det.conf[t:t + 1], det.area)
        if bool((one.conf > 0).any()):
            prev = fit_poses(term, skeleton, one, prev, iterations)
        out.append(prev[0])
    return torch.stack(out)


def detection_nll(pix: torch.Tensor, det: Detections, scales: torch.Tensor,
                  calibration: torch.Tensor) -> torch.Tensor:
    """Summed negative log-likelihood of the valid detections given the expected pixels
    ``pix (T, C, K', 2)`` (:func:`~torchmocap.likelihoods.keypoints_learned.expected_pixels`),
    the scales ``(C, K')`` and the calibration's parameters, under the mixture of the module
    docstring (differentiable in all three)."""
    valid = det.conf > 0
    s = scales.to(pix)
    z = ((pix - det.uv.to(pix)) ** 2).sum(-1) / (s * s)
    log_t = -math.log(math.pi) - 2.0 * s.log() - 2.0 * torch.log1p(z)
    g = monotone_calibration(det.conf.to(pix), calibration).clamp(1e-6, 1.0 - 1e-6)
    ll = torch.logaddexp(g.log() + log_t, torch.log1p(-g) - math.log(det.area))
    return -torch.where(valid, ll, torch.zeros_like(ll)).sum()


def _whitened(term, settings: KeypointTrainSettings) -> list[torch.Tensor]:
    """The term's parameters in units of their prior std (what L-BFGS moves: one unit is a
    comparable change of each): offsets' change, camera log-scales, keypoint log-factors,
    calibration, pixel biases."""
    with torch.no_grad():
        return [(term.offsets - term.base_offsets) / settings.offset_prior_m,
                term.log_scale_px.clone(), term.log_keypoint_scale / settings.scale_prior,
                term.calibration.clone(),
                term.pixel_bias / settings.bias_prior if settings.bias_prior else
                term.pixel_bias.clone()]


def _values(term, u: list[torch.Tensor], settings: KeypointTrainSettings) -> dict:
    return {"offsets": term.base_offsets.to(u[0]) + settings.offset_prior_m * u[0],
            "log_scale_px": u[1], "log_keypoint_scale": settings.scale_prior * u[2],
            "calibration": u[3],
            "pixel_bias": settings.bias_prior * u[4] if settings.bias_prior else u[4]}


def fit_parameters(term, skeleton, theta: torch.Tensor, det: Detections,
                   settings: KeypointTrainSettings) -> tuple[float, torch.Tensor]:
    """Fit the term's parameters to the detections under the poses ``theta (T, D)``: L-BFGS
    (in units of the priors' stds) on :func:`detection_nll` plus the Gaussian priors
    (module docstring), per valid detection — with ``settings.joint`` the poses too (then
    clamped into the skeleton's limits) —, then the calibration alone under the rest. Returns
    the final negative log-likelihood per detection and the poses ``(T, D)``."""
    u = _whitened(term, settings)
    free = u if settings.bias_prior else u[:4]  # bias_prior 0: the biases stay
    for x in free:
        x.requires_grad_(True)
    theta = theta.detach().to(skeleton.offsets.dtype).clone().requires_grad_(settings.joint)
    with torch.no_grad():
        fixed = None if settings.joint else Poses(theta, skeleton).kinematics
    rig = term.rig
    n = max(det.num_valid, 1)
    opt = torch.optim.LBFGS(free + ([theta] if settings.joint else []), lr=1.0,
                            max_iter=settings.parameter_iterations, history_size=20,
                            line_search_fn="strong_wolfe")

    def nll():
        v = _values(term, u, settings)
        kin = fixed if fixed is not None else Poses(theta, skeleton).kinematics
        x = keypoint_positions(kin.positions, kin.rotations, term.kmap, v["offsets"])
        return detection_nll(expected_pixels(rig, x, v["pixel_bias"]), det,
                             keypoint_scales(v["log_scale_px"], v["log_keypoint_scale"]),
                             v["calibration"])

    def closure():
        opt.zero_grad()
        prior = sum((x * x).sum() for x in (u[0], u[2])) \
            + ((u[4] * u[4]).sum() if settings.bias_prior else 0.0)
        loss = (nll() + 0.5 * prior) / n
        loss.backward()
        return loss

    opt.step(closure)
    # the calibration alone under the fitted rest (cheap: the pixels are fixed); in the joint
    # problem its few, strongly coupled parameters converge slowly
    with torch.no_grad():
        v = _values(term, u, settings)
        kin = fixed if fixed is not None else Poses(theta, skeleton).kinematics
        pix = expected_pixels(rig, keypoint_positions(kin.positions, kin.rotations, term.kmap,
                                                      v["offsets"]), v["pixel_bias"])
        scales = keypoint_scales(v["log_scale_px"], v["log_keypoint_scale"])
    cal = u[3]
    opt = torch.optim.LBFGS([cal], lr=1.0, max_iter=settings.parameter_iterations,
                            history_size=20, line_search_fn="strong_wolfe")

    def calibration_closure():
        opt.zero_grad()
        loss = detection_nll(pix, det, scales, cal) / n
        loss.backward()
        return loss

    opt.step(calibration_closure)
    with torch.no_grad():
        final = float(nll()) / n
        for name, v in _values(term, u, settings).items():
            getattr(term, name).copy_(v)
    return final, skeleton.clamp(theta.detach())


def train_keypoint_term(term, skeleton, det: Detections, theta0: torch.Tensor,
                        settings: KeypointTrainSettings, progress=None) -> dict:
    """Alternating maximum likelihood of the term's parameters on the training detections
    (module docstring).

    Args:
        term: a :class:`~torchmocap.likelihoods.LearnedKeypointLikelihood` on the training
            views' rig.
        skeleton: the subject's skeleton.
        det: the training frames' :class:`Detections` (:func:`stack_detections`,
            :meth:`Detections.frames`).
        theta0: ``(D,)`` the first frame's starting pose.
        settings: :class:`KeypointTrainSettings`.
        progress: optional ``f(message)`` called after every round.

    Returns:
        ``{"theta": (T, D) the last poses, "history": [{round, nll_per_detection,
        energy_per_frame}], "settings": ..., "detections": the number of valid detections}``.

    Raises:
        ValueError: bad settings, no valid detection.
    """
    settings.check()
    if det.num_valid == 0:
        raise ValueError("data: no valid keypoint detection in the training frames and views")
    theta = track_poses(term, skeleton, det, theta0.to(skeleton.offsets.dtype),
                        settings.pose_iterations)
    history = []
    for r in range(settings.rounds):
        nll, theta = fit_parameters(term, skeleton, theta, det, settings)
        theta = fit_poses(term, skeleton, det, theta, settings.pose_iterations)
        with torch.no_grad():
            e = float(_energy_fn(term, skeleton, det)(theta).mean())
        history.append({"round": r + 1, "nll_per_detection": nll, "energy_per_frame": e})
        if progress is not None:
            progress(f"round {r + 1}/{settings.rounds}: NLL/detection {nll:.4f}, "
                     f"energy/frame {e:.2f}")
    return {"theta": theta, "history": history, "settings": asdict(settings),
            "detections": det.num_valid}
