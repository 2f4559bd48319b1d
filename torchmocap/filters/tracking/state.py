"""Typed records of a track: the tracker's state between frames (:class:`TrackState`, what a
checkpoint stores), each frame's diagnostics (:class:`FrameInfo`) and the finished
:class:`Track`. The frame before a step reaches the inference and the proposal as a
:class:`~torchmocap.proposals.PreviousFrame` (:meth:`TrackState.previous_frame`).

Shapes: ``T`` frames, ``D`` DoFs, ``P`` particles, ``K`` hypotheses.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import torch

from torchmocap.proposals.base import PreviousFrame

__all__ = ["FrameInfo", "Track", "TrackState"]


@dataclass
class FrameInfo:
    """Diagnostics of one frame of a track (``Track.infos[t]``), JSON-friendly values.

    Attributes:
        frame: the frame index.
        initial: frame 0 (the given start, or its refinement).
        seconds: tracking time of the frame (frame 0: all of its set-up — refinement, body
            fit, refit passes — when there was any).
        energy: ``{term: energy}`` of the estimate, per likelihood term.
        ess: effective sample size per annealing layer (an SIR filter: one value).
        beta: the annealing exponent per layer.
        proposal: the proposal's statistics (acceptance rates, tries, fallbacks; summed counts
            and mean rates over the frame's layers).
        refine: a refinement stage's statistics (energies before and after, which start won).
        no_evidence: the likelihood terms without usable evidence in this frame, and
            ``"imu"`` when only a proposal (or the estimator) reads the IMUs and every tracking
            sample is dropped.
        hypotheses: ``K x D`` modes kept by a multi-hypothesis inference.
        hypothesis_weights: their ``K`` weights; mode_energy: their ``K`` energies.
        body_fit: the body fit of the first frame (IoU and energy before/after, scales).
        refit: the refit passes of the first frame (each with its ``body_fit``).
        batch_size: tracks evaluated together in a batch (:func:`~torchmocap.filters.track_groups`).
        inference: the inference's other diagnostics (e.g. ``min_energy`` per layer,
            ``seconds_inference``, ``rounds``, a mixture's ``minima``).
    """

    frame: int
    initial: bool = False
    seconds: float | None = None
    energy: dict[str, float] = field(default_factory=dict)
    ess: list[float] = field(default_factory=list)
    beta: list[float] = field(default_factory=list)
    proposal: dict[str, Any] = field(default_factory=dict)
    refine: dict[str, float] | None = None
    no_evidence: list[str] = field(default_factory=list)
    hypotheses: list | None = None
    hypothesis_weights: list[float] | None = None
    mode_energy: list[float] | None = None
    body_fit: dict[str, Any] | None = None
    refit: list[dict[str, Any]] | None = None
    batch_size: int | None = None
    inference: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, info: dict[str, Any], **fields: Any) -> FrameInfo:
        """A record from an inference's diagnostics dict (``InferenceResult.info``): its keys
        that name a field fill that field, the others go to :attr:`inference`; ``fields``
        (e.g. ``frame``, ``seconds``) are set as given."""
        names = {f.name for f in dataclasses.fields(cls)} - {"inference"}
        typed = {k: v for k, v in info.items() if k in names}
        rest = {k: v for k, v in info.items() if k not in names}
        if isinstance(info.get("inference"), dict):
            rest = {**info["inference"], **rest}
            rest.pop("inference", None)
        return cls(**{**typed, **fields}, inference=rest)


@dataclass
class TrackState:
    """Tracker state between frames (what a checkpoint stores).

    Attributes:
        history: ``(<=3, D)`` last estimates, oldest first.
        frame: index of the last tracked frame.
        generator_state: the random generator's state.
        estimates: ``T`` estimates ``(D,)`` so far.
        infos: per-frame :class:`FrameInfo`.
        particles, log_weights: the last frame's particle set ``(P, D)`` and its normalised log
            weights ``(P,)`` (None when the inference keeps none).
        carry: what the inference keeps for the next frame (``InferenceResult.carry``).
    """

    history: torch.Tensor
    frame: int
    generator_state: torch.Tensor
    estimates: list = field(default_factory=list)
    infos: list[FrameInfo] = field(default_factory=list)
    particles: torch.Tensor | None = None
    log_weights: torch.Tensor | None = None
    carry: dict | None = None

    def previous_frame(self) -> PreviousFrame:
        """What the next frame's inference may use of this state."""
        return PreviousFrame(estimate=self.history[-1], history=self.history,
                             particles=self.particles, log_weights=self.log_weights,
                             carry=self.carry)

    def to_dict(self) -> dict[str, Any]:
        """Plain containers of tensors and numbers (a checkpoint's payload)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrackState:
        """The inverse of :meth:`to_dict` (infos as :class:`FrameInfo`)."""
        d = dict(d)
        d["infos"] = [i if isinstance(i, FrameInfo) else FrameInfo.from_dict(i)
                      for i in d.get("infos", [])]
        return cls(**d)


@dataclass
class Track:
    """Output of :meth:`~torchmocap.filters.Tracker.run`.

    Attributes:
        theta: ``(T, D)`` estimates (frame 0 is the initial pose); smoothed when the tracker
            has a ``smoother``.
        infos: ``T`` per-frame :class:`FrameInfo` (ESS and beta per layer, timings, proposal
            statistics).
        seconds_per_frame: mean tracking time of frames 1..T-1.
        filtered: ``(T, D)`` the filtered (per-frame) estimates when ``theta`` is smoothed,
            else ``None``.
        smoother: the smoother's report when ``theta`` is smoothed (its name, what it fitted
            or chose; a chain's has one report per stage under ``stages``, each with its
            output track under ``theta``), else ``None``.
    """

    theta: torch.Tensor
    infos: list[FrameInfo]
    seconds_per_frame: float
    filtered: torch.Tensor | None = None
    smoother: dict[str, Any] | None = None
