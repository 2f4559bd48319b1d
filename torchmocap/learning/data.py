"""Training data for learned likelihoods: frames, true poses and negatives from many clips.

A *clip* entry (the ``data.clip`` keys of ``torchmocap-track``: ``name``, ``path``, ``asf``,
``start``, ``frames``, ...) and a scenario give a synthesised sequence (the skinned body, the
scenario's corruptions). Every ``stride``-th frame becomes a :class:`TrainingFrame`: the frame
as a tracker sees it, the true pose, and **negatives** — poses the tracker would consider:

- *proposal draws*: ``proposal_negatives`` draws of the tracker's own proposal (``P``: the
  sensor-manifold proposal with von Mises-Fisher noise) around the true pose, at the spreads
  ``scales`` (factors on the proposal's std), as a tracker's layer 0 and mutations are drawn;
- *hard negatives*: ``hard_negatives`` particles of the tracker's final layer, running the
  tracker over the clip — the poses its energy prefers (its errors). ``overrides`` (Hydra
  overrides of the tracker preset) mine them with another tracker, e.g. the learned likelihood
  of a previous round (``likelihood@tracker.likelihood=image_learned``,
  ``tracker.likelihood.terms.learned.weights=<file>``): the minima the learned energy prefers
  wrongly become negatives of the next round. The proposal draws and the base energy always
  come from the plain preset.

Sequences and negatives are built once and cached (``cache_dir``): an entry's key hashes the
clip, scenario, seed and negative settings.
Shapes: ``K`` negatives, ``D`` pose DoF.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

__all__ = ["ClipData", "NegativeSettings", "TrainingFrame", "build_clip_data",
           "load_clip_set", "pose_errors"]


@dataclass
class NegativeSettings:
    """How negatives are drawn (see the module docstring)."""

    tracker: str = "p"
    num_particles: int = 100
    proposal_negatives: int = 16
    scales: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
    hard_negatives: int = 16
    stride: int = 2
    overrides: tuple[str, ...] = ()

    def key(self) -> dict[str, Any]:
        return {"tracker": self.tracker, "num_particles": self.num_particles,
                "overrides": list(self.overrides),
                "proposal_negatives": self.proposal_negatives,
                "scales": [float(s) for s in self.scales], "hard_negatives": self.hard_negatives,
                "stride": self.stride}


@dataclass
class TrainingFrame:
    """One training sample: ``frame`` (as the tracker sees it), ``truth (D,)``,
    ``negatives (K, D)``, and the index of its clip in :class:`ClipData` lists."""

    frame: Any
    truth: torch.Tensor
    negatives: torch.Tensor
    clip: int = 0


@dataclass
class ClipData:
    """A synthesised clip with its runtime (skeleton, body, rig, calibrated tracker) and
    samples."""

    name: str
    sequence: Any
    runtime: Any
    tracker: Any
    frames: list[TrainingFrame] = field(default_factory=list)


def pose_errors(skeleton, theta: torch.Tensor, truth: torch.Tensor,
                rotation_weight: float = 0.0) -> torch.Tensor:
    """Mean joint position error (metres) of poses ``theta (K, D)`` against ``truth (D,)``,
    plus ``rotation_weight`` (metres per radian) times the mean geodesic angle between their
    joint rotations (bone twist, which positions do not see): ``(K,)``."""
    ka = skeleton(theta, check_finite=False)
    kb = skeleton(truth[None], check_finite=False)
    err = (ka.positions - kb.positions).norm(dim=-1).mean(-1)
    if rotation_weight > 0:
        rel = ka.rotations.transpose(-1, -2) @ kb.rotations
        cos = ((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
        err = err + rotation_weight * torch.arccos(cos).mean(-1)
    return err


def _cache_key(clip: Mapping[str, Any], scenario: str, overrides: Mapping[str, Any], seed: int,
               neg: NegativeSettings) -> str:
    blob = json.dumps({"clip": dict(clip), "scenario": scenario, "overrides": dict(overrides),
                       "seed": seed, "negatives": neg.key(), "version": 1}, sort_keys=True,
                      default=str)
    name = str(clip.get("name") or "clip")
    return f"{name}-{hashlib.sha256(blob.encode()).hexdigest()[:12]}"


def _negatives(tracker, sequence, neg: NegativeSettings, seed: int, progress: bool = False,
               miner=None) -> dict[int, torch.Tensor]:
    """``{frame index: negatives (K, D)}`` for the frames kept (every ``stride``-th, from 1):
    proposal draws of ``tracker`` and the particle sets of ``miner`` (default: ``tracker``)."""
    from torchmocap.filters.tracking.tracker import initial_pose
    from torchmocap.proposals.base import ProposalContext

    g = torch.Generator().manual_seed(seed)
    tracking = None if sequence.imu is None else sequence.imu.tracking.nonzero()[:, 0]
    gt = sequence.ground_truth
    miner = tracker if miner is None else miner
    frame0 = tracker.observe(sequence.frame(0), tracking)
    theta0 = initial_pose(sequence).to(tracker.dtype)
    if miner is not tracker:
        tracker.init(theta0, frame0)  # calibrates the proposal's sensors
    state = miner.init(theta0, frame0)
    out: dict[int, torch.Tensor] = {}
    T = sequence.num_frames
    for t in range(1, T):
        frame = tracker.observe(sequence.frame(t), tracking)
        if neg.hard_negatives > 0:
            state, _, _ = miner.step(state, frame)
        if (t - 1) % neg.stride:
            continue
        truth = gt.theta[t].to(tracker.dtype)
        parts = []
        if neg.proposal_negatives > 0:
            per = [neg.proposal_negatives // len(neg.scales)] * len(neg.scales)
            per[-1] += neg.proposal_negatives - sum(per)
            for s, k in zip(neg.scales, per):
                if k == 0:
                    continue
                ctx = ProposalContext(previous=truth, sensors=tracker._sensors(frame),
                                      sensor_valid=frame.imu_valid, frame=frame, scale=float(s))
                parts.append(tracker.proposal.sample(ctx, k, g).particles.detach())
        if neg.hard_negatives > 0 and state.particles is not None:
            p = state.particles
            idx = torch.randperm(p.shape[0], generator=g)[:neg.hard_negatives]
            parts.append(torch.cat([state.estimates[-1][None], p[idx[:-1]]]))
        out[t] = torch.cat(parts).to(tracker.dtype)
    return out


def build_clip_data(clip: Mapping[str, Any], scenario: str = "outdoor",
                    scenario_overrides: Mapping[str, Any] | None = None, seed: int = 0,
                    negatives: NegativeSettings | None = None,
                    cache_dir: str | Path | None = None, progress: bool = False) -> ClipData:
    """Synthesise ``clip`` under ``scenario`` and draw its negatives (cached under
    ``cache_dir`` when given)."""
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data import Sequence as Seq
    from torchmocap.data.synthetic.clips import synthesized_sequence

    neg = negatives or NegativeSettings()
    overrides = {"depth.enabled": False, "joints2d.enabled": False,
                 **dict(scenario_overrides or {})}
    clip = dict(clip)
    entry = None
    seq = None
    negs = None
    if cache_dir is not None:
        entry = Path(cache_dir) / _cache_key(clip, scenario, overrides, seed, neg)
        if (entry / "negatives.pt").is_file() and (entry / "sequence").is_dir():
            try:
                seq = Seq.load(entry / "sequence")
                negs = torch.load(entry / "negatives.pt", weights_only=True)
            except Exception:  # unreadable: rebuild
                seq = negs = None
    rebuilt = seq is None
    if rebuilt:
        seq = synthesized_sequence(clip, scenario, overrides, seed=seed)
    runtime = Runtime.from_sequence(seq)
    tracker = build_tracker(tracker_config(neg.tracker, [
        f"tracker.num_particles={neg.num_particles}"]), runtime, seed=seed)
    if negs is None:
        miner = tracker
        if neg.overrides:
            miner = build_tracker(tracker_config(neg.tracker, [
                f"tracker.num_particles={neg.num_particles}", *neg.overrides]), runtime,
                seed=seed)
        negs = _negatives(tracker, seq, neg, seed, progress, miner=miner)
    else:  # calibrate the tracking sensors as the negatives' run did (frame 0)
        from torchmocap.filters.tracking.tracker import initial_pose

        tracking = None if seq.imu is None else seq.imu.tracking.nonzero()[:, 0]
        tracker.init(initial_pose(seq).to(tracker.dtype),
                     tracker.observe(seq.frame(0), tracking))
    if entry is not None and rebuilt:
        seq.save(entry / "sequence", overwrite=True)
        tmp = entry / "negatives.pt.tmp"
        torch.save({int(k): v for k, v in negs.items()}, tmp)
        tmp.replace(entry / "negatives.pt")
    tracking = None if seq.imu is None else seq.imu.tracking.nonzero()[:, 0]
    data = ClipData(str(clip.get("name") or "clip"), seq, runtime, tracker)
    for t, n in sorted(negs.items()):
        frame = tracker.observe(seq.frame(int(t)), tracking)
        data.frames.append(TrainingFrame(frame, seq.ground_truth.theta[int(t)].to(
            tracker.dtype), n))
    return data


def load_clip_set(clips: Sequence[Mapping[str, Any]], scenarios: Sequence[str],
                  seeds: Sequence[int], negatives: NegativeSettings | None = None,
                  cache_dir: str | Path | None = None, scenario_overrides=None,
                  progress: bool = True) -> list[ClipData]:
    """:func:`build_clip_data` for every clip x scenario x synthesis seed; the frames'
    ``clip`` index points into the returned list."""
    from tqdm import tqdm

    jobs = [(c, s, sd) for c in clips for s in scenarios for sd in seeds]
    out: list[ClipData] = []
    for c, s, sd in tqdm(jobs, desc="data", unit="clip", disable=not progress):
        d = build_clip_data(c, s, scenario_overrides, int(sd), negatives, cache_dir)
        d.name = f"{d.name}/{s}/{sd}"
        for f in d.frames:
            f.clip = len(out)
        out.append(d)
    return out

