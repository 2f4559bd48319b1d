"""The frame-by-frame tracker: the loop that composes a predictor, a proposal, a likelihood, an
inference algorithm and an estimator.

Per frame ``t``:

1. the **predictor** extrapolates the next pose from the last estimates (Pons-Moll: AR(3));
2. the **likelihood** prepares the frame's observations once (``prepare``) and is bound to them
   as an energy ``V(theta) -> (P,)`` (:class:`~torchmocap.likelihoods.FrameEnergy`);
3. the **inference** module (annealing, local descent, ...) draws particles from the
   **proposal** around the prediction, weighs / optimises them against ``V``, and the
   **estimator** turns the final particle set into the estimate (eq. 18);
4. the estimate (clamped to the joint limits) joins the history.

The tracker owns nothing but that loop, the random generator, checkpoints (every
:class:`~torchmocap.stateful.Stateful` component saves its own state in them) and the sensor
calibration at frame 0 (eq. 8). Which paper method it is depends only on the components it is
built from (``conf/tracker/*.yaml``); it never dispatches on a method name. Every component
declares the observation modalities it reads (``requires``): :meth:`Tracker.run` refuses a
sequence that lacks one, naming it.

The tracker never sees ground truth or validation sensors: :meth:`Tracker.observe` strips them
from each frame. All randomness flows from one ``torch.Generator`` seeded by ``seed``: the same
seed gives an identical track, also across a checkpoint and resume.
Shapes: ``P`` particles, ``D`` DoF, ``S`` tracking sensors.
"""

from __future__ import annotations

import dataclasses
import os
import time

import torch
from torch import nn

from torchmocap.filters.inference.base import Inference
from torchmocap.filters.smoothing.base import Smoother
from torchmocap.filters.tracking.body_fit import BodyFit
from torchmocap.filters.tracking.estimators import Estimator
from torchmocap.filters.tracking.state import FrameInfo, Track, TrackState
from torchmocap.likelihoods.base import FrameEnergy, Likelihood
from torchmocap.proposals.base import Proposal, ProposalContext
from torchmocap.stateful import Stateful

__all__ = [
    "SEED_RANGE",
    "CheckpointError",
    "MissingObservationError",
    "Tracker",
    "check_checkpoint",
    "check_seed",
    "check_working_memory",
]

#: the components that declare the observation modalities they read (``requires``)
_COMPONENTS = (Likelihood, Proposal, Estimator)
#: the format version of :meth:`Tracker.save_checkpoint` (3: components save their own state)
CHECKPOINT_VERSION = 3
#: the seeds a ``torch.Generator`` takes (its 64-bit state; negative seeds wrap around)
SEED_RANGE = (-(2 ** 63), 2 ** 64 - 1)


class MissingObservationError(ValueError):
    """A tracker needs a modality the sequence or frame does not provide."""


class CheckpointError(ValueError):
    """A checkpoint cannot be resumed by this tracker (other settings, data or format)."""


def check_seed(seed, name: str = "seed") -> int:
    """``seed`` as a generator seed: an integer in :data:`SEED_RANGE` (``1.5`` and ``True``
    are errors naming ``name``, not seeds 1; ``2**64`` cannot seed a generator)."""
    import numbers

    lo, hi = SEED_RANGE
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or \
            not lo <= seed <= hi:
        raise ValueError(f"{name}: expected an integer in [-2**63, 2**64 - 1] (a generator's "
                         f"seed), got {seed!r}")
    return int(seed)


def check_checkpoint(path: str | os.PathLike | None, every) -> None:
    """Check checkpoint settings before a track starts: ``every`` an integer >= 1 and, with a
    ``path``, its directory existing and writable (not found out at the first save, frames
    into the track).

    Raises:
        ValueError: ``checkpoint_every`` or ``checkpoint`` (named) is invalid.
    """
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"checkpoint_every: expected an integer >= 1 (frames between saves), "
                         f"got {every!r}")
    if path is None:
        return
    p = os.path.abspath(os.fspath(path))
    if os.path.isdir(p):
        raise ValueError(f"checkpoint: {p} is a directory; expected a file path")
    parent = os.path.dirname(p)
    if not os.path.isdir(parent):
        raise ValueError(f"checkpoint: the directory {parent} does not exist (create it, or "
                         "choose another checkpoint path)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"checkpoint: the directory {parent} is not writable")


def check_working_memory(trackers) -> None:
    """Refuse trackers (tracked together) whose particle sets cannot fit in memory: each frame
    holds at least every particle's pose and the 4x4 frames of every joint
    (:meth:`Tracker.working_memory`), before any likelihood's own buffers.

    Raises:
        MemoryBudgetError: naming ``num_particles``.
    """
    from torchmocap.memory import check_memory

    trackers = list(trackers)
    t = trackers[0]
    n = sum(tr.num_particles for tr in trackers)
    check_memory(sum(tr.working_memory() for tr in trackers),
                 f"{n} particles ({t.skeleton.num_dofs} DoFs and the 4x4 frames of "
                 f"{t.skeleton.num_joints} joints each, {t.dtype})", "num_particles", t.device)


def _check_component(obj, kind, name: str):
    if not isinstance(obj, kind):
        raise TypeError(f"{name}: expected a {kind.__module__}.{kind.__name__}, got "
                        f"{type(obj).__name__}")
    return obj


def _check_descent_energy(inference: Inference, likelihood: Likelihood) -> None:
    """An inference that takes gradients of the energy (``differentiates_energy``: a
    :class:`LocalInference`, alone or as a ``refine`` stage, or a mixture's local optimisation)
    needs a differentiable energy (:attr:`~torchmocap.likelihoods.Likelihood.differentiable`):
    a descent would otherwise silently ignore the term (and autograd refuses its kernels)."""
    users = [type(m).__name__ for m in inference.modules()
             if isinstance(m, Inference) and m.differentiates_energy]
    if not users:
        return
    for name, m in likelihood.named_modules():
        if isinstance(m, Likelihood) and not m.differentiable and not any(
                isinstance(c, Likelihood) for c in m.modules() if c is not m):
            where = f"likelihood.{name}" if name else "likelihood"
            raise ValueError(f"{where}: {users[0]} takes gradients of the energy and needs "
                             f"{m.differentiable_hint or 'a differentiable term'}")


class Tracker(nn.Module):
    """Tracks a skeleton through per-frame observations, assembled from components.

    Args:
        skeleton: the tracking model (joint limits; forward kinematics of the energy).
        predictor: ``history (T, D) -> (D,)``
            (:class:`~torchmocap.filters.PosePredictor`).
        proposal: a :class:`~torchmocap.proposals.Proposal`.
        likelihood: a :class:`~torchmocap.likelihoods.Likelihood` (energy convention).
        inference: an :class:`~torchmocap.filters.inference.Inference`.
        estimator: an :class:`~torchmocap.filters.Estimator`.
        num_particles: ``P``.
        manifold: the :class:`~torchmocap.ik.SensorManifold` of the tracking IMUs, calibrated
            on the first frame (eq. 8) when given; the proposal, likelihood and estimator that
            use sensors share it.
        seed: seed of the tracker's generator.
        name: label (progress bar, metrics), e.g. the preset name.
        refine_first_frame: run the inference on frame 0 too, from the given initial pose (or
            a set of candidate poses ``(K, D)``) — for fits of a real frame from a rough start.
        body_fit: optional :class:`~torchmocap.filters.tracking.body_fit.BodyFit` started at
            :meth:`init` once the first pose is known, e.g.
            :class:`~torchmocap.filters.SilhouetteBodyFit` (fits the capsule radii — and axis
            offsets — to the first frame, and with ``refine_first_frame`` refines that pose
            again with the fitted body: its ``refit_passes``).
        smoother: optional :class:`~torchmocap.filters.smoothing.Smoother` applied to the
            finished track (:meth:`run`): ``Track.theta`` is then the smoothed track and
            ``Track.filtered`` the per-frame estimates (which alone feed the prediction).
    """

    def __init__(self, skeleton, predictor, proposal: Proposal, likelihood: Likelihood,
                 inference: Inference, estimator: Estimator, num_particles: int = 200,
                 manifold=None, seed: int = 0, name: str = "tracker",
                 refine_first_frame: bool = False, body_fit: BodyFit | None = None,
                 smoother: Smoother | None = None) -> None:
        super().__init__()
        if isinstance(num_particles, bool) or not isinstance(num_particles, int) \
                or num_particles < 1:
            raise ValueError(f"num_particles: expected an int >= 1, got {num_particles!r}")
        seed = check_seed(seed)
        if not callable(predictor):
            raise TypeError(f"predictor: expected a callable, got {type(predictor).__name__}")
        self.skeleton = skeleton
        self.predictor = predictor
        self.proposal = _check_component(proposal, Proposal, "proposal")
        self.likelihood = _check_component(likelihood, Likelihood, "likelihood")
        self.inference = _check_component(inference, Inference, "inference")
        self.estimator = _check_component(estimator, Estimator, "estimator")
        _check_descent_energy(self.inference, self.likelihood)
        self.manifold = manifold
        self.num_particles = num_particles
        self.seed = seed
        self.name = str(name)
        self.refine_first_frame = bool(refine_first_frame)
        self.body_fit = None if body_fit is None else _check_component(body_fit, BodyFit,
                                                                        "body_fit")
        self.smoother = None if smoother is None else _check_component(smoother, Smoother,
                                                                        "smoother")
        # modalities read by the proposal or estimator only (P's sensor-manifold proposal reads
        # the IMUs): a frame without evidence of one is reported like a likelihood term without
        # evidence (a likelihood term reports its own)
        self._outside_likelihood = tuple(
            m for c in (self.proposal, self.estimator) for m in c.requires
            if m not in self.likelihood.requires)
        if smoother is not None:
            smoother.check(self.inference)

    @property
    def dtype(self) -> torch.dtype:
        """The tracking dtype: the skeleton's (follows ``tracker.to(...)``, ``.double()``)."""
        return self.skeleton.offsets.dtype

    @property
    def device(self) -> torch.device:
        """Where the tracker computes: the skeleton's device (``tracker.to("cuda")``)."""
        return self.skeleton.offsets.device

    def working_memory(self) -> int:
        """Bytes a frame holds at least: ``P x (D + 16 J)`` numbers of the tracking dtype —
        every particle's pose and the 4x4 frames of its ``J`` joints (the forward kinematics
        every likelihood evaluates); the likelihood's own buffers come on top."""
        sk = self.skeleton
        item = torch.finfo(self.dtype).bits // 8
        return self.num_particles * (sk.num_dofs + 16 * sk.num_joints) * item

    def _on_device(self, frame):
        """``frame`` with its tensors on the tracker's device (a no-op when they are)."""
        dev = self.device
        moved = {f.name: v.to(dev) for f in dataclasses.fields(frame)
                 if isinstance(v := getattr(frame, f.name), torch.Tensor) and v.device != dev}
        return dataclasses.replace(frame, **moved) if moved else frame

    # ------------------------------------------------------------------ observations
    @property
    def requires(self) -> tuple[str, ...]:
        """Observation modalities the components read (union, in order)."""
        mods: list[str] = []
        for c in (self.likelihood, self.proposal, self.estimator):
            mods += [m for m in c.requires if m not in mods]
        return tuple(mods)

    def check_sequence(self, sequence) -> None:
        """Raise :class:`MissingObservationError` naming the first modality the components
        need and the sequence lacks, and a ``ValueError`` for a sequence that still holds the
        camera it holds out (:func:`~torchmocap.data.split_heldout`)."""
        from torchmocap.data.heldout import heldout_camera

        held = heldout_camera(sequence)
        if held is not None:
            raise ValueError(f"tracker {self.name!r}: the sequence still holds its held-out "
                             f"camera {held!r}; track split_heldout(sequence)[0] and score the "
                             "track in the held-out view")
        have = sequence.modalities
        for m in self.requires:
            if m not in have:
                users = self.users_of(m)
                raise MissingObservationError(
                    f"tracker {self.name!r} needs {m!r} observations (for {', '.join(users)}); "
                    f"the sequence has {', '.join(have) or 'none'}")
        if "imu" in self.requires and self.manifold is None:
            raise MissingObservationError(
                f"tracker {self.name!r} needs tracking IMUs, but none of the sequence's sensors "
                "is a tracking sensor")

    def users_of(self, modality: str) -> list[str]:
        """``"path (Class)"`` of the innermost components that read ``modality``."""
        out = []
        for path, mod in self.named_modules():
            if not path or not isinstance(mod, _COMPONENTS) or modality not in mod.requires:
                continue
            inner = [c for _, c in mod.named_modules() if c is not mod
                     and isinstance(c, _COMPONENTS) and modality in c.requires]
            if not inner:
                out.append(f"{path} ({type(mod).__name__})")
        return out

    @staticmethod
    def observe(frame, tracking: torch.Tensor | None = None):
        """What a tracker may see of a :class:`~torchmocap.data.Frame`: the tracking IMUs only
        (``tracking``: their indices or a bool mask), their orientations as rotation matrices
        ``imu (S, 3, 3)`` (converted once per frame; every component reading IMUs takes
        either form), no ground truth."""
        from torchmocap.ik.sensor_manifold import sensor_rotations

        imu, valid = frame.imu, frame.imu_valid
        if imu is not None and tracking is not None:
            imu = imu[tracking]
            valid = None if valid is None else valid[tracking]
        if imu is not None:
            imu = sensor_rotations(imu, imu.shape[-2] if imu.shape[-1] == 4 else imu.shape[-3],
                                   "frame.imu")
        return dataclasses.replace(frame, imu=imu, imu_valid=valid, theta=None, positions=None,
                                   rotations=None)

    def _check_frame(self, frame) -> None:
        for m in self.requires:
            if getattr(frame, m, None) is None:
                raise MissingObservationError(f"tracker {self.name!r}: frame {frame.index} has "
                                              f"no {m!r} observations")

    def _sensors(self, frame) -> torch.Tensor | None:
        if frame.imu is None or self.manifold is None:
            return None
        from torchmocap.ik.sensor_manifold import sensor_rotations

        return sensor_rotations(frame.imu, self.manifold.num_sensors).to(self.dtype)

    def _context(self, previous: torch.Tensor, frame) -> ProposalContext:
        return ProposalContext(previous=previous, sensors=self._sensors(frame),
                               sensor_valid=frame.imu_valid, frame=frame)

    def frame_energy(self, frame) -> FrameEnergy:
        """The likelihood bound to one frame's observations: ``V(theta (P, D)) -> (P,)``
        (the frame as the tracker may see it, on the tracker's device)."""
        return FrameEnergy(self.likelihood, self.likelihood.prepare(frame), self.skeleton)

    def _infer(self, context: ProposalContext, frame, generator: torch.Generator,
               energy: FrameEnergy | None = None):
        if energy is None:
            energy = self.frame_energy(frame)
        res = self.inference(energy, self.proposal, self.estimator, context,
                             self.num_particles, generator)
        est = res.estimate.detach().to(self.dtype)
        # every estimate within the joint limits
        est = torch.maximum(torch.minimum(est, self.skeleton.upper.to(est.dtype)),
                            self.skeleton.lower.to(est.dtype))
        with torch.no_grad():
            terms = {k: float(v[0]) for k, v in energy.terms(est[None]).items()}
        missing = list(energy.missing_evidence())
        missing += [m for m in self._outside_likelihood
                    if not frame.has_evidence(m) and m not in missing]
        if missing:  # terms without usable evidence in this frame (uninformative)
            res.info["no_evidence"] = missing
        return est, res, terms

    # ------------------------------------------------------------------ state
    def init(self, theta0: torch.Tensor, frame0=None, seed: int | None = None) -> TrackState:
        """Start from a known first pose ``(D,)`` — or candidate poses ``(K, D)`` when
        ``refine_first_frame`` — and calibrate the tracking sensors on frame 0 (eq. 8).

        ``frame0`` is the first frame as the tracker may see it (:meth:`observe`); ``seed``
        seeds this track's generator (default: the tracker's ``seed``)."""
        D = self.skeleton.num_dofs
        if not isinstance(theta0, torch.Tensor) or theta0.shape[-1:] != (D,) \
                or theta0.dim() not in (1, 2) or (theta0.dim() == 2
                                                   and not self.refine_first_frame):
            shape = tuple(theta0.shape) if isinstance(theta0, torch.Tensor) else type(theta0)
            raise ValueError(f"theta0: expected shape ({D},)"
                             f"{' or (K, ' + str(D) + ')' if self.refine_first_frame else ''}, "
                             f"got {shape}")
        if not bool(torch.isfinite(theta0).all()):
            raise ValueError("theta0: expected finite values, found NaN or inf")
        theta0 = theta0.to(device=self.device, dtype=self.dtype)
        if frame0 is not None:
            frame0 = self._on_device(frame0)
        g = torch.Generator(device=theta0.device).manual_seed(self.seed if seed is None
                                                               else int(seed))
        info = FrameInfo(frame=0, initial=True)
        particles = log_w = carry = None
        t_init = time.perf_counter()
        if self.refine_first_frame:
            if frame0 is None:
                raise ValueError("frame0: required to refine the first frame")
            self._check_frame(frame0)
            t0 = time.perf_counter()
            est, res, terms = self._infer(self._context(theta0, frame0), frame0, g)
            info = FrameInfo.from_dict(res.info, frame=0, initial=True,
                                       seconds=time.perf_counter() - t0, energy=terms)
            theta0, particles, log_w, carry = est, res.particles, res.log_weights, res.carry
        if self.body_fit is not None and frame0 is not None:
            refine = self._refiner(frame0, g) if self.refine_first_frame else None
            theta0, kept, info.body_fit, passes = self.body_fit.start(theta0, frame0, refine)
            if passes is not None:
                info.refit = passes
            if kept is not None:
                particles, log_w, carry = kept.particles, kept.log_weights, kept.carry
            # the whole first frame: the refinement, the body fit and the refit passes
            info.seconds = time.perf_counter() - t_init
        if self.manifold is not None and frame0 is not None and frame0.imu is not None:
            self.manifold.calibrate(theta0, self._sensors(frame0))
        return TrackState(history=theta0[None].clone(), frame=0, generator_state=g.get_state(),
                          estimates=[theta0.clone()], infos=[info], particles=particles,
                          log_weights=log_w, carry=carry)

    def _refiner(self, frame0, g: torch.Generator):
        """``refine(theta (D,), scale) -> (estimate, result, energies (2,))``: the inference on
        the first frame from ``theta`` with the proposal's spread scaled, and the energies of
        ``theta`` and the estimate (the body as it is then) — the refit passes of a
        :class:`~torchmocap.filters.tracking.body_fit.BodyFit`."""

        def refine(theta: torch.Tensor, scale: float):
            energy = self.frame_energy(frame0)
            ctx = dataclasses.replace(self._context(theta, frame0), scale=scale)
            est, res, _ = self._infer(ctx, frame0, g, energy)
            with torch.no_grad():
                v = energy(torch.stack([theta, est]))
            return est, res, v

        return refine

    # ------------------------------------------------------------------ one frame
    def step(self, state: TrackState, frame, energy: FrameEnergy | None = None
             ) -> tuple[TrackState, torch.Tensor, FrameInfo]:
        """Track one frame (as the tracker may see it, :meth:`observe`): returns the new
        state, the estimate ``(D,)`` and the frame's diagnostics. ``energy``: the frame's
        :meth:`frame_energy` when the caller built it already (batched tracking shares one
        among the tracks of a batch, :mod:`torchmocap.filters.tracking.batched`)."""
        self._check_frame(frame)
        frame = self._on_device(frame)
        g = torch.Generator(device=state.history.device).manual_seed(self.seed)
        g.set_state(state.generator_state)
        t0 = time.perf_counter()
        pred = self.predictor(state.history)
        # the previous frame's particle set and whatever the inference carries between frames
        context = dataclasses.replace(self._context(pred, frame),
                                      previous_frame=state.previous_frame())
        est, res, terms = self._infer(context, frame, g, energy)
        info = FrameInfo.from_dict(res.info, frame=state.frame + 1,
                                   seconds=time.perf_counter() - t0, energy=terms)
        new = TrackState(
            history=torch.cat([state.history, est[None]])[-3:],
            frame=state.frame + 1,
            generator_state=g.get_state(),
            estimates=state.estimates + [est],
            infos=state.infos + [info],
            particles=None if res.particles is None else res.particles.detach(),
            log_weights=None if res.log_weights is None else res.log_weights.detach(),
            carry=res.carry,
        )
        return new, est, info

    # ------------------------------------------------------------------ whole sequences
    def run(self, sequence, theta0: torch.Tensor | None = None, progress: bool = True,
            checkpoint: str | None = None, checkpoint_every: int = 10,
            stop_after: int | None = None, fingerprint: str | None = None,
            callbacks=()) -> Track:
        """Track every frame of a :class:`~torchmocap.data.Sequence`.

        Args:
            sequence: observations. The first pose is ``theta0``, else the ground truth of
                frame 0, else ``sequence.meta.initial_poses`` (candidates refined on frame 0;
                a single one is the first pose of a tracker that does not refine it).
            progress: show a tqdm progress bar.
            checkpoint: file to save the state to every ``checkpoint_every`` frames; when it
                exists the run resumes from it (same seed: same track as an uninterrupted run).
                Its directory must exist (:func:`check_checkpoint`).
            stop_after: stop after this many frames (to simulate an interruption).
            fingerprint: identity of the run (settings + data); stored in the checkpoint and
                compared on resume (:class:`CheckpointError` on a mismatch).
            callbacks: callables ``(state, info)`` run after every frame (e.g. a
                :class:`~torchmocap.threads.ThreadGovernor`).
        """
        from tqdm import tqdm

        check_checkpoint(checkpoint, checkpoint_every)
        self.check_sequence(sequence)
        check_working_memory([self])
        tracking = None
        if sequence.imu is not None:
            tracking = sequence.imu.tracking.nonzero()[:, 0]
        if theta0 is None:
            theta0 = self.first_pose(sequence)
        T = sequence.num_frames
        state = None
        if checkpoint is not None and os.path.exists(checkpoint):
            state = self.load_checkpoint(checkpoint, fingerprint, num_frames=T)
        if state is None:
            state = self.init(theta0, self.observe(sequence.frame(0), tracking))
        bar = tqdm(range(state.frame + 1, T), disable=not progress, desc=f"track[{self.name}]",
                   unit="frame")
        done = 0
        for t in bar:
            state, _, info = self.step(state, self.observe(sequence.frame(t), tracking))
            bar.set_postfix(s=f"{info.seconds:.2f}")
            for cb in callbacks:
                cb(state, info)
            done += 1
            if checkpoint is not None and (t % checkpoint_every == 0 or t == T - 1):
                self.save_checkpoint(state, checkpoint, fingerprint)
            if stop_after is not None and done >= stop_after:
                if checkpoint is not None:
                    self.save_checkpoint(state, checkpoint, fingerprint)
                break
        secs = [i.seconds for i in state.infos[1:] if i.seconds is not None]
        return self.finish(Track(theta=torch.stack(state.estimates), infos=state.infos,
                                 seconds_per_frame=float(sum(secs) / max(len(secs), 1))))

    def first_pose(self, sequence) -> torch.Tensor:
        """The start of a track of ``sequence`` (:func:`initial_pose`): ``(D,)``, or the
        candidates ``(K, D)`` for a tracker that refines the first frame (a single candidate
        is the pose itself)."""
        theta0 = initial_pose(sequence)
        if theta0.dim() == 2 and not self.refine_first_frame:
            if theta0.shape[0] != 1:
                raise ValueError(
                    f"tracker {self.name!r}: the sequence offers {theta0.shape[0]} candidate "
                    "first poses (meta.initial_poses) and the tracker does not refine the "
                    "first frame to choose one (refine_first_frame: true, e.g. "
                    "tracker=real_frame)")
            theta0 = theta0[0]
        return theta0

    def finish(self, track: Track) -> Track:
        """The track as returned: smoothed by the ``smoother`` if there is one."""
        return track if self.smoother is None else self.smoother.smooth(track)

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, state: TrackState, path: str, fingerprint: str | None = None
                        ) -> None:
        """Atomically write the state, and every :class:`~torchmocap.stateful.Stateful`
        component's own (the sensor calibration, a fitted body), to ``path``."""
        from torchmocap.atomic import atomic_path

        payload = {"format": "torchmocap-track-checkpoint", "version": CHECKPOINT_VERSION,
                   "state": state.to_dict(), "name": self.name, "seed": self.seed,
                   "fingerprint": fingerprint,
                   "components": {path: m.checkpoint_state() for path, m in self.named_modules()
                                  if isinstance(m, Stateful)}}
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:  # a file object: the archive name is not the temporary one
                torch.save(payload, f)

    def load_checkpoint(self, path: str, fingerprint: str | None = None,
                        num_frames: int | None = None) -> TrackState:
        """Read a state written by :meth:`save_checkpoint` (plain tensors only: loaded with
        ``weights_only=True``). Raises :class:`CheckpointError` when it was written by another
        tracker name, seed or fingerprint, or is longer than the sequence."""
        try:
            payload = torch.load(path, weights_only=True)
        except Exception as e:  # not a checkpoint (junk, text, a directory, foreign pickle)
            raise CheckpointError(f"checkpoint {path}: not a torchmocap tracker checkpoint "
                                  f"({type(e).__name__})") from None
        if not isinstance(payload, dict) or payload.get("format") != \
                "torchmocap-track-checkpoint":
            raise CheckpointError(f"checkpoint {path}: not a torchmocap tracker checkpoint")
        if payload.get("name") != self.name or payload.get("seed") != self.seed:
            raise CheckpointError(
                f"checkpoint {path}: written by tracker {payload.get('name')!r} seed "
                f"{payload.get('seed')}, not {self.name!r} seed {self.seed}")
        if payload.get("fingerprint") != fingerprint:
            raise CheckpointError(
                f"checkpoint {path}: written for other settings or data (fingerprint "
                f"{payload.get('fingerprint')} != {fingerprint}); remove it to start over")
        state = TrackState.from_dict(payload["state"])
        if num_frames is not None and state.frame >= num_frames:
            raise CheckpointError(f"checkpoint {path}: has {state.frame + 1} frames, the "
                                  f"sequence only {num_frames}")
        components = payload.get("components")
        if payload.get("version") != CHECKPOINT_VERSION or not isinstance(components, dict):
            raise CheckpointError(f"checkpoint {path}: written by another version of torchmocap "
                                  f"(format version {payload.get('version')}, expected "
                                  f"{CHECKPOINT_VERSION}); remove it to start over")
        ours = {p: m for p, m in self.named_modules() if isinstance(m, Stateful)}
        if set(components) != set(ours):
            raise CheckpointError(f"checkpoint {path}: holds the state of components "
                                  f"{sorted(components)}, this tracker has {sorted(ours)}")
        for p, st in components.items():
            ours[p].load_checkpoint_state(st)
        return state

    def extra_repr(self) -> str:
        return f"name={self.name!r}, num_particles={self.num_particles}, seed={self.seed}"


def initial_pose(sequence) -> torch.Tensor:
    """The first pose of a track: the ground truth of frame 0, else the candidate poses
    ``(K, D)`` in ``sequence.meta.initial_poses`` (real recordings)."""
    if sequence.ground_truth is not None:
        return sequence.ground_truth.theta[0]
    init = sequence.meta.initial_poses
    if init is None:
        raise ValueError("theta0: required when the sequence has neither ground truth nor "
                         "meta.initial_poses")
    return torch.as_tensor(init, dtype=torch.float32)


def start_pose(sequence) -> torch.Tensor:
    """One pose ``(D,)`` to start a fit from: :func:`initial_pose`, its first candidate when
    there are several."""
    theta = initial_pose(sequence)
    return theta[0] if theta.dim() == 2 else theta
