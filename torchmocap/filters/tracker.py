"""Frame-by-frame trackers of Pons-Moll et al. (2010): P, G, GS, RS (annealed) and L, LS (local).

Per frame: predict from the last three estimates (3rd-order autoregression, root rotation
composed on SO(3), clamped to the joint limits), spread particles around the prediction, then

- ``p``:  annealed particle optimisation in the *active* space of the sensor manifold; every
  evaluation maps active coordinates and a per-particle noisy set of the measured tracking-sensor
  orientations through the analytic ``g^{-1}`` (noise: ``vmf`` on S^3 (the paper), ``gaussian``
  on the passive joint parameters, ``tangent`` Gaussian, or ``none``). The estimate is
  ``g^{-1}`` of the weighted mean of the active coordinates with the measured sensors (eq. 18).
- ``g``:  the same optimiser in the full 31-DoF space on the image cost only.
- ``gs``: full space, image cost plus the sensor-orientation cost.
- ``rs``: full space, image cost; every diffusion step is rejection-sampled until every
  tracking sensor's angular error is at most ``reject_deg`` (capped; the best try is kept).
- ``l`` / ``ls``: gradient-based local optimisation of the smooth image cost (plus the
  orientation cost for ``ls``) from the prediction.

The image cost is ``V = w_silh V_silh + w_app V_app`` (eq. 17; paper ``2`` and ``40``). All
randomness flows from one ``torch.Generator`` seeded by ``seed``: a fixed seed gives an
identical track. Shapes: ``P`` particles, ``D`` DoF, ``C`` views, ``S`` tracking sensors.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field

import torch

from torchmocap.distributions import VonMisesFisher
from torchmocap.filters.annealed import GeometricDiffusion, anneal, default_diffusion
from torchmocap.filters.local import minimise_local
from torchmocap.filters.prediction import AutoregressivePredictor, RotationGroup
from torchmocap.geometry import (
    axis_angle_rotation,
    axis_angle_to_quaternion,
    quaternion_to_matrix,
)
from torchmocap.ik.sensor_manifold import SensorManifold
from torchmocap.likelihoods.appearance import (
    appearance_energy,
    body_surface_pattern,
    prepare_images,
)
from torchmocap.likelihoods.orientation import orientation_energy
from torchmocap.likelihoods.silhouette import prepare_silhouettes, silhouette_energy

__all__ = [
    "METHODS",
    "MissingObservationError",
    "Track",
    "TrackState",
    "Tracker",
    "TrackerConfig",
    "frame_observation",
]

METHODS = ("p", "g", "gs", "rs", "l", "ls")
NOISES = ("vmf", "gaussian", "tangent", "none")


class MissingObservationError(ValueError):
    """A tracker needs a modality the sequence does not provide."""


@dataclass
class TrackerConfig:
    """Settings of :class:`Tracker` (the fields of ``conf/tracker/*.yaml``)."""

    method: str = "p"
    num_particles: int = 200
    layers: int = 15
    noise: str = "vmf"
    kappa: float = 1000.0
    gaussian_std_deg: float = 3.6
    sigma_rot_deg: float = 3.0
    sigma_trans: float = 0.02
    diffusion: str = "covariance"
    diffusion_decay: float = math.sqrt(0.5)
    selection: str = "multinomial"
    w_silh: float = 2.0
    w_app: float = 40.0
    w_ori: float = 2.0
    ori_cost: str = "squared"
    reject_deg: float = 10.0
    reject_tries: int = 200
    predictor: str = "damped"
    damping: tuple[float, float] = (0.8, 0.3)
    fg_samples: int = 64
    app_axial: int = 3
    app_around: int = 4
    local_iterations: int = 40
    local_lr: float = 0.02

    @classmethod
    def preset(cls, name: str, **overrides) -> TrackerConfig:
        """The bundled ``conf/tracker/<name>.yaml`` (what ``tracker=<name>`` selects on the
        command line), with ``overrides`` applied on top.

        Example:
            >>> TrackerConfig.preset("gs", num_particles=100).ori_cost
            'linear'
        """
        from pathlib import Path

        from omegaconf import OmegaConf

        root = Path(__file__).resolve().parents[1] / "conf" / "tracker"

        def load(n: str, seen: tuple = ()) -> dict:
            path = root / f"{n}.yaml"
            if not path.is_file() or n in seen:
                names = sorted(q.stem for q in root.glob("*.yaml"))
                raise ValueError(f"name: unknown tracker preset {n!r}; expected one of {names}")
            own = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
            defaults = own.pop("defaults", [])
            out: dict = {}
            for item in defaults + ([] if "_self_" in defaults else ["_self_"]):
                out.update(own if item == "_self_" else load(item, seen + (n,)))
            return out

        spec = load(name)
        spec.update(overrides)
        if "damping" in spec:
            spec["damping"] = tuple(spec["damping"])
        return cls(**spec)

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {self.method!r}")
        if self.noise not in NOISES:
            raise ValueError(f"noise: expected one of {NOISES}, got {self.noise!r}")
        if self.ori_cost not in ("linear", "squared"):
            raise ValueError(f"ori_cost: expected 'linear' or 'squared', got {self.ori_cost!r}")
        if self.diffusion not in ("covariance", "geometric"):
            raise ValueError(
                f"diffusion: expected 'covariance' or 'geometric', got {self.diffusion!r}"
            )
        if self.num_particles < 1 or self.layers < 1:
            raise ValueError("num_particles and layers: expected integers >= 1")
        self.damping = tuple(float(x) for x in self.damping)


@dataclass
class TrackState:
    """Tracker state between frames (what a checkpoint stores)."""

    history: torch.Tensor  # (<=3, D) last estimates, oldest first
    frame: int
    generator_state: torch.Tensor
    estimates: list = field(default_factory=list)
    infos: list = field(default_factory=list)


@dataclass
class Track:
    """Output of :meth:`Tracker.run`.

    Attributes:
        theta: ``(T, D)`` estimates (frame 0 is the initial pose).
        infos: per-frame diagnostics (ESS and beta per layer, timings, acceptance).
        seconds_per_frame: mean tracking time of frames 1..T-1.
    """

    theta: torch.Tensor
    infos: list
    seconds_per_frame: float


def frame_observation(frame, tracking: torch.Tensor | None = None) -> dict:
    """Observation dict of a :class:`~torchmocap.data.sequence.Frame` for :meth:`Tracker.step`;
    ``tracking`` selects the tracking IMUs ``(S,)`` (index or bool)."""
    obs = {"silhouettes": frame.silhouettes, "images": frame.images}
    if frame.view_dropped is not None:
        obs["view_valid"] = ~frame.view_dropped.bool()
    if frame.imu is not None:
        sel = slice(None) if tracking is None else tracking
        obs["imu"] = frame.imu[sel]
        if frame.imu_valid is not None:
            obs["imu_valid"] = frame.imu_valid[sel]
    return obs


class Tracker:
    """Tracks a subject skeleton through per-frame observations.

    Args:
        body: a :class:`~torchmocap.body.CapsuleBody` of the subject (its ``skeleton`` is the
            tracking model).
        rig: the :class:`~torchmocap.cameras.CameraRig` of the silhouettes/images.
        config: :class:`TrackerConfig`.
        sensors: ``{sensor: bone}`` of the tracking IMUs (needed by p, gs, rs, ls).
        seed: seed of the tracker's generator.
    """

    def __init__(
        self,
        body,
        rig,
        config: TrackerConfig | None = None,
        sensors: dict[str, str] | None = None,
        seed: int = 0,
    ):
        self.cfg = config or TrackerConfig()
        self.body = body
        self.skeleton = body.skeleton
        self.rig = rig
        self.dtype = self.skeleton.offsets.dtype
        self.seed = int(seed)
        sk = self.skeleton
        self.lower = sk.lower.clone()
        self.upper = sk.upper.clone()
        self.uses_sensors = self.cfg.method in ("p", "gs", "rs", "ls")
        self.sensors = dict(sensors or {})
        if self.uses_sensors and not self.sensors:
            raise MissingObservationError(
                f"tracker {self.cfg.method!r} needs tracking IMUs: pass sensors={{name: bone}}"
            )
        self.manifold = SensorManifold(sk, self.sensors) if self.uses_sensors else None
        self.pattern = (body_surface_pattern(body, self.cfg.app_axial, self.cfg.app_around)
                        if self.cfg.w_app > 0 else None)
        axes = torch.tensor(sk.joint_axes[0], dtype=torch.float64)
        root = sk.joint_dofs(sk.joint_names[0])[-3:]

        def to_matrix(t, axes=axes):
            a = axes.to(t.dtype)
            return (
                axis_angle_rotation(a[0].expand_as(t), t[..., 0])
                @ axis_angle_rotation(a[1].expand_as(t), t[..., 1])
                @ axis_angle_rotation(a[2].expand_as(t), t[..., 2])
            )

        groups = [RotationGroup(tuple(root), to_matrix=to_matrix)] if len(root) == 3 else []
        self.predictor = AutoregressivePredictor(
            self.cfg.predictor,
            damping=self.cfg.damping,
            rotation_groups=groups,
            lower=self.lower,
            upper=self.upper,
        )
        sig = torch.full((sk.num_dofs,), math.radians(self.cfg.sigma_rot_deg), dtype=self.dtype)
        sig[sk.translation_dofs] = self.cfg.sigma_trans
        self.sigma_full = sig
        self._vmf = None  # the sensor-noise distribution, built on first use

    # ------------------------------------------------------------------ observations
    def _check_frame(self, obs: dict) -> None:
        if obs.get("silhouettes") is None:
            raise MissingObservationError(f"tracker {self.cfg.method!r} needs silhouettes")
        if self.cfg.w_app > 0 and obs.get("images") is None:
            raise MissingObservationError(
                f"tracker {self.cfg.method!r} needs colour images for the appearance term "
                "(set w_app=0 to track on silhouettes alone)"
            )
        if self.uses_sensors and obs.get("imu") is None:
            raise MissingObservationError(
                f"tracker {self.cfg.method!r} needs tracking IMU orientations ('imu')"
            )

    def _image_energy(self, obs: dict, prepared, smooth: bool = False):
        cfg = self.cfg
        rig = self.rig
        colours = prepare_images(obs["images"], self.dtype) if cfg.w_app > 0 else None

        def energy(theta: torch.Tensor) -> torch.Tensor:
            kin = self.skeleton(theta, check_finite=False)
            ep = self.body.endpoints(kin)
            v = cfg.w_silh * silhouette_energy(ep, self.body.radii, rig, prepared, smooth=smooth)
            if cfg.w_app > 0:
                v = v + cfg.w_app * appearance_energy(
                    kin, self.body, self.pattern, rig, colours, prepared.view_valid, endpoints=ep
                )
            return v

        return energy

    def _sensor_rotations(self, obs: dict) -> torch.Tensor:
        imu = obs["imu"].to(self.dtype)
        return quaternion_to_matrix(imu) if imu.shape[-1] == 4 else imu

    def _orientation_energy(self, obs: dict):
        R_ts = self._sensor_rotations(obs)  # measured R_TS (S, 3, 3)
        R_bs = self.manifold.sensor_to_bone.to(self.dtype).transpose(-1, -2)  # R_BS = R_SB^T
        bones = self.manifold._bone_index
        valid = obs.get("imu_valid")

        def energy(theta):
            R = self.skeleton(theta, check_finite=False).rotations[..., bones, :, :]
            return orientation_energy(R, R_bs, R_ts, valid,
                                      1 if self.cfg.ori_cost == "linear" else 2)

        return energy

    # ------------------------------------------------------------------ state
    def init(self, theta0: torch.Tensor, obs0: dict | None = None) -> TrackState:
        """Start from a known first pose (and calibrate the sensors on frame 0, eq. 8)."""
        theta0 = theta0.to(self.dtype)
        if theta0.shape != (self.skeleton.num_dofs,):
            raise ValueError(
                f"theta0: expected shape ({self.skeleton.num_dofs},), got {tuple(theta0.shape)}"
            )
        if self.uses_sensors:
            if obs0 is None or obs0.get("imu") is None:
                raise MissingObservationError(
                    f"tracker {self.cfg.method!r} needs the first frame's IMUs to calibrate"
                )
            self.manifold.calibrate(theta0, self._sensor_rotations(obs0))
        g = torch.Generator().manual_seed(self.seed)
        return TrackState(
            history=theta0[None].clone(),
            frame=0,
            generator_state=g.get_state(),
            estimates=[theta0.clone()],
            infos=[{"frame": 0, "initial": True}],
        )

    def _predict(self, history: torch.Tensor) -> torch.Tensor:
        if history.shape[0] >= 3:
            return self.predictor(history[-3:].double()).to(self.dtype)
        if history.shape[0] == 2:
            pred = history[-1] + 0.5 * (history[-1] - history[-2])
            return torch.maximum(torch.minimum(pred, self.upper), self.lower)
        return history[-1].clone()

    # ------------------------------------------------------------------ one frame
    def step(self, state: TrackState, obs: dict) -> tuple[TrackState, torch.Tensor, dict]:
        """Track one frame: returns the new state, the estimate ``(D,)`` and diagnostics."""
        self._check_frame(obs)
        cfg = self.cfg
        g = torch.Generator().manual_seed(self.seed)
        g.set_state(state.generator_state)
        t0 = time.perf_counter()
        pred = self._predict(state.history)
        smooth = cfg.method in ("l", "ls")  # the blurred masks serve only the smooth cost
        prepared = prepare_silhouettes(
            obs["silhouettes"], cfg.fg_samples, blur=1.5 if smooth else 0.0,
            view_valid=obs.get("view_valid"), dtype=self.dtype
        )
        image_energy = self._image_energy(obs, prepared, smooth=smooth)
        info: dict = {"frame": state.frame + 1}
        P = cfg.num_particles
        if cfg.method == "p":
            est, res = self._track_manifold(pred, obs, image_energy, g)
        elif cfg.method in ("g", "gs", "rs"):
            energy = image_energy
            if cfg.method == "gs":
                ori = self._orientation_energy(obs)

                def energy(theta, _img=image_energy, _ori=ori):
                    return _img(theta) + cfg.w_ori * _ori(theta)

            x0 = pred + self.sigma_full * torch.randn(
                P, pred.shape[0], generator=g, dtype=self.dtype
            )
            diffusion = self._diffusion(self.sigma_full)
            if cfg.method == "rs":
                base = GeometricDiffusion(self.sigma_full, cfg.diffusion_decay)
                diffusion = self._rejection_diffusion(base, obs, info)
                x0 = diffusion(pred.expand(P, -1).clone(), -1, g)
            res = anneal(
                energy,
                x0,
                layers=cfg.layers,
                selection=cfg.selection,
                diffusion=diffusion,
                lower=self.lower,
                upper=self.upper,
                generator=g,
            )
            est = res.estimate
        else:
            est, res = self._track_local(pred, obs, image_energy)
        est = torch.maximum(torch.minimum(est.detach(), self.upper), self.lower)
        info["seconds"] = time.perf_counter() - t0
        if res is not None:
            info["beta"] = [float(b) for b in res.beta]
            info["ess"] = [float(e) for e in res.ess]
            info["min_energy"] = [float(e) for e in res.min_energy]
        hist = torch.cat([state.history, est[None]])[-3:]
        new = TrackState(
            history=hist,
            frame=state.frame + 1,
            generator_state=g.get_state(),
            estimates=state.estimates + [est],
            infos=state.infos + [info],
        )
        return new, est, info

    def _diffusion(self, sigma0: torch.Tensor):
        """Per-layer mutation: the diagonal particle covariance (Gall's ISA, cooled 10x over
        the layers) or PARSEC-style per-DoF ``sigma0 * decay^k``."""
        if self.cfg.diffusion == "covariance":
            return default_diffusion(self.cfg.layers)
        return GeometricDiffusion(sigma0, self.cfg.diffusion_decay)

    def _sensor_noise(self, P: int, S: int, g: torch.Generator) -> torch.Tensor | None:
        """Per-particle sensor noise rotations ``R_w`` as quaternions ``(P, S, 4)`` (or None)."""
        cfg = self.cfg
        if cfg.noise == "vmf":
            if self._vmf is None:
                mu = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=self.dtype)
                self._vmf = VonMisesFisher(mu, cfg.kappa)
            return self._vmf.sample((P, S), generator=g)
        if cfg.noise == "tangent":
            w = torch.randn(P, S, 3, generator=g, dtype=self.dtype) * (2.0 / math.sqrt(cfg.kappa))
            return axis_angle_to_quaternion(w)
        return None

    def _track_manifold(self, pred, obs, image_energy, g):
        cfg = self.cfg
        m = self.manifold
        P = cfg.num_particles
        R_ts = self._sensor_rotations(obs)
        act = m.active_index
        passive = m.passive_index.reshape(-1)
        sig_a = self.sigma_full[act]
        gstd = math.radians(cfg.gaussian_std_deg)

        def decode(xa):
            noise = self._sensor_noise(xa.shape[0], R_ts.shape[0], g)
            theta = m.inverse(xa, R_ts, reference=pred, noise=noise, compute_residual=False,
                              validate=False).theta
            if cfg.noise == "gaussian":
                noise = (
                    torch.randn(theta.shape[0], passive.numel(), generator=g, dtype=theta.dtype)
                    * gstd
                )
                theta = theta.clone()
                theta[:, passive] = theta[:, passive] + noise
            return theta

        x0 = pred[act] + sig_a * torch.randn(P, act.numel(), generator=g, dtype=self.dtype)
        res = anneal(
            image_energy,
            x0,
            layers=cfg.layers,
            selection=cfg.selection,
            diffusion=self._diffusion(sig_a),
            lower=self.lower[act],
            upper=self.upper[act],
            decode=decode,
            generator=g,
        )
        est = m.inverse(res.estimate[None], R_ts, reference=pred, compute_residual=False).theta[0]
        return est, res

    def _rejection_diffusion(self, base, obs, info):
        """Diffusion whose every sample satisfies all sensor constraints to ``reject_deg``."""
        cfg = self.cfg
        R_ts = self._sensor_rotations(obs)
        R_bs = self.manifold.sensor_to_bone.to(self.dtype).transpose(-1, -2)
        bones = self.manifold._bone_index
        thr = math.radians(cfg.reject_deg)
        stats = {"tries": 0, "accepted": 0, "proposed": 0}
        info["rejection"] = stats

        def worst_error(theta):
            from torchmocap.geometry import geodesic_angle

            R = self.skeleton(theta, check_finite=False).rotations[:, bones]
            return geodesic_angle(R @ R_bs, R_ts).max(-1).values

        def diffusion(particles, step, generator):
            out = particles.clone()
            best = torch.full((particles.shape[0],), math.inf, dtype=self.dtype)
            todo = torch.ones(particles.shape[0], dtype=torch.bool)
            for _ in range(cfg.reject_tries):
                idx = todo.nonzero()[:, 0]
                if idx.numel() == 0:
                    break
                cand = base(particles[idx], max(step, 0), generator)
                cand = torch.maximum(torch.minimum(cand, self.upper), self.lower)
                err = worst_error(cand)
                stats["tries"] += 1
                stats["proposed"] += int(idx.numel())
                ok = err <= thr
                improve = err < best[idx]
                out[idx[improve]] = cand[improve]
                best[idx[improve]] = err[improve]
                stats["accepted"] += int(ok.sum())
                todo[idx[ok]] = False
            stats["acceptance_rate"] = stats["accepted"] / max(stats["proposed"], 1)
            stats["unfilled"] = int(todo.sum())
            return out

        return diffusion

    def _track_local(self, pred, obs, image_energy):
        """L / LS: Adam on the smooth image cost (+ orientation cost) from the prediction."""
        cfg = self.cfg
        ori = self._orientation_energy(obs) if cfg.method == "ls" else None

        def energy(theta):
            v = image_energy(theta)
            return v if ori is None else v + cfg.w_ori * ori(theta)

        res = minimise_local(energy, pred[None], method="adam", iterations=cfg.local_iterations,
                             lower=self.lower, upper=self.upper, lr=cfg.local_lr)
        return res.x[0], None

    # ------------------------------------------------------------------ whole sequences
    def run(self, sequence, theta0: torch.Tensor | None = None, progress: bool = True,
            checkpoint: str | None = None, checkpoint_every: int = 10,
            stop_after: int | None = None) -> Track:
        """Track every frame of a :class:`~torchmocap.data.Sequence`.

        Args:
            sequence: observations (and ground truth, whose frame-0 pose starts the track unless
                ``theta0`` is given).
            progress: show a tqdm progress bar.
            checkpoint: file to save the state to every ``checkpoint_every`` frames; when it
                exists the run resumes from it (same seed: same track as an uninterrupted run).
            stop_after: stop after this many frames (to simulate an interruption).
        """
        from tqdm import tqdm

        tracking = None
        if self.uses_sensors:
            if sequence.imu is None:
                raise MissingObservationError(
                    f"tracker {self.cfg.method!r} needs IMUs; the sequence has "
                    f"{sequence.modalities}")
            tracking = torch.tensor([i for i, t in enumerate(sequence.imu.tracking.tolist())
                                     if t])
        if sequence.silhouettes is None:
            raise MissingObservationError(
                f"tracker {self.cfg.method!r} needs silhouettes; the sequence has "
                f"{sequence.modalities}")
        if theta0 is None:
            if sequence.ground_truth is None:
                raise ValueError("theta0: required when the sequence has no ground truth")
            theta0 = sequence.ground_truth.theta[0]
        T = sequence.num_frames
        state = None
        if checkpoint is not None and os.path.exists(checkpoint):
            state = self.load_checkpoint(checkpoint)
        if state is None:
            state = self.init(theta0, frame_observation(sequence.frame(0), tracking))
        start = state.frame + 1
        bar = tqdm(range(start, T), disable=not progress, desc=f"track[{self.cfg.method}]",
                   unit="frame")
        done = 0
        for t in bar:
            state, _, info = self.step(state, frame_observation(sequence.frame(t), tracking))
            bar.set_postfix(s=f"{info['seconds']:.2f}")
            done += 1
            if checkpoint is not None and (t % checkpoint_every == 0 or t == T - 1):
                self.save_checkpoint(state, checkpoint)
            if stop_after is not None and done >= stop_after:
                if checkpoint is not None:
                    self.save_checkpoint(state, checkpoint)
                break
        secs = [i["seconds"] for i in state.infos if "seconds" in i]
        return Track(theta=torch.stack(state.estimates), infos=state.infos,
                     seconds_per_frame=float(sum(secs) / max(len(secs), 1)))

    def save_checkpoint(self, state: TrackState, path: str) -> None:
        """Atomically write the state (and the sensor calibration) to ``path``."""
        payload = {"state": state.__dict__, "method": self.cfg.method, "seed": self.seed,
                   "sensor_to_bone": None if self.manifold is None
                   else self.manifold.sensor_to_bone.clone()}
        tmp = f"{path}.tmp"
        torch.save(payload, tmp)
        os.replace(tmp, path)

    def load_checkpoint(self, path: str) -> TrackState:
        """Read a state written by :meth:`save_checkpoint` (same method and seed required)."""
        payload = torch.load(path, weights_only=False)
        if payload.get("method") != self.cfg.method or payload.get("seed") != self.seed:
            raise ValueError(f"checkpoint {path}: written by method {payload.get('method')!r} "
                             f"seed {payload.get('seed')}, not {self.cfg.method!r} seed "
                             f"{self.seed}")
        if self.manifold is not None and payload["sensor_to_bone"] is not None:
            self.manifold.sensor_to_bone = payload["sensor_to_bone"]
        return TrackState(**payload["state"])
