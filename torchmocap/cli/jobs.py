"""The steps of one ``torchmocap-track`` job that a single run and a batch of seeds share:
the thread policy, the early check of the tracker settings, and :func:`finish` — a track's
scores (:func:`torchmocap.evaluation.evaluate_track`), its files and ``metrics.json``."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from typing import Any

from torchmocap.atomic import write_json_atomic
from torchmocap.cli.runs import is_multirun

__all__ = ["finish", "thread_policy", "validate_tracker"]


def thread_policy(cfg):
    """Set torch's thread count by the ``threads`` setting (:mod:`torchmocap.threads`: ``auto``
    stays off cores that other processes or parallel jobs of the sweep use); returns the
    governor that re-checks between frames."""
    from torchmocap.threads import ThreadGovernor

    launcher = None
    if is_multirun():
        from hydra.core.hydra_config import HydraConfig

        launcher = HydraConfig.get().launcher
    return ThreadGovernor.start(cfg.get("threads", "auto"), launcher)


def validate_tracker(cfg) -> None:
    """Build the tracker once against a stand-in subject (human31, four cameras, the paper's
    five tracking IMUs): a bad setting — also a particle count whose particle sets cannot fit
    in memory, or a tracker needing observations the data source never provides (IMUs of a
    video recording, :func:`~torchmocap.data.sources.check_source_modalities`) — fails in a
    fraction of a second, before the data is loaded, fitted and synthesised."""
    from hydra.utils import get_object

    from torchmocap.assembly import Runtime, build_tracker
    from torchmocap.body import CapsuleBody
    from torchmocap.cameras import make_ring_rig
    from torchmocap.data.sources import check_source_modalities
    from torchmocap.filters.tracking.tracker import check_seed, check_working_memory
    from torchmocap.ik import SensorManifold
    from torchmocap.skeleton import human31

    seed = check_seed(cfg.get("seed"))
    sk = human31()
    stand_in = Runtime(skeleton=sk, body=CapsuleBody(sk).float(), rig=make_ring_rig(4).float(),
                       manifold=SensorManifold(sk))
    with warnings.catch_warnings():  # about the stand-in's data (its camera names), not the run's
        warnings.simplefilter("ignore")
        tracker = build_tracker(cfg.tracker, stand_in, seed=seed)
    check_working_memory([tracker])
    source = get_object(cfg.data._target_)
    check_source_modalities(source, tracker.requires, tracker.name, _data_name(cfg),
                            tracker.users_of)


def _data_name(cfg) -> str:
    """``data=<choice>`` of the run (the data source's target outside a Hydra run)."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        choice = HydraConfig.get().runtime.choices.get("data")
        if choice:
            return f"data={choice}"
    return f"the data source {cfg.data._target_}"


def finish(cfg, out: Path, seq, runtime, tracker, track, fingerprint: str,
           extra: dict | None = None) -> dict:
    """Score a finished track, write its files and ``metrics.json`` (last); returns the metrics
    (``extra`` joins them). ``seq`` is the run's whole sequence: with a held-out camera
    (``evaluation.heldout_camera``) the track is of its other views and is scored in that one
    (:func:`~torchmocap.data.split_heldout`); the overlays show every view. The evaluation's
    warnings are printed as ``torchmocap-track: warning: ...``."""
    from torchmocap.cli.outputs import write_outputs
    from torchmocap.data import split_heldout
    from torchmocap.evaluation import EvaluationWarning, evaluate_track

    metrics: dict[str, Any] = {
        "tracker": tracker.name,
        "frames": int(track.theta.shape[0]),
        "tracked_frames": int(track.theta.shape[0] - 1),
        "seconds_per_frame": track.seconds_per_frame,
        "num_particles": tracker.num_particles,
        "layers": getattr(tracker.inference, "layers", None),
        "scenario": seq.scenario,
        "seed": int(cfg.seed),
        "clip": seq.meta.clip or {},
        "fingerprint": fingerprint,
    }
    tracked, heldout = split_heldout(seq)
    evaluation = cfg.get("evaluation") or {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", EvaluationWarning)
        scores = evaluate_track(tracked, runtime, tracker, track, energy_vs_truth=bool(
            cfg.get("diagnostics", {}).get("energy_vs_truth", False)), heldout=heldout,
            min_confidence=float(evaluation.get("min_confidence", 0.3)))
    for w in caught:
        if issubclass(w.category, EvaluationWarning):
            print(f"torchmocap-track: warning: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    metrics.update(extra or {})
    metrics.update(scores.metrics)
    fitted = None if tracker.body_fit is None else tracker.body_fit.fitted_mesh()
    write_outputs(out, cfg, seq, runtime, track.theta, scores.arrays, fitted_mesh=fitted)
    write_json_atomic(metrics, out / "metrics.json")
    return metrics
