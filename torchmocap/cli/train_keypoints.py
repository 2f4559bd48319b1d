"""``torchmocap-train --config-name train_keypoints``: fit the keypoint likelihood's hand-set
parts (offsets, scales, confidence calibration) to a recording, without ground truth.

The recording (``data=recording``, any folder of docs/recordings.md) is loaded without masks; with
``evaluation.heldout_camera=<cam>`` that camera is kept out of the training, and the first
``train_frames`` frames of the other cameras are the training data
(:func:`~torchmocap.learning.keypoints.train_keypoint_term`). Then both the hand-set term and the
learned one fit every frame of the training cameras (frame by frame, each from the previous
fit) and are scored in the held-out camera on the frames not trained on (``test``) and on the
trained ones (``train``): cross-validation across cameras and across time. Without a held-out
camera the training views' own errors on the test frames are reported.

Outputs in the run directory: ``keypoints.pt`` (the weights file; ``export=<path>`` writes a
copy, e.g. into ``torchmocap/assets/learned/``) and ``summary.json`` (settings, the training's
history, the learned offsets in centimetres per keypoint, the scales, the calibration at its
knots, the scores and the seconds).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

__all__ = ["parameter_report", "run", "train_frame_count"]


def train_frame_count(value, num_frames: int) -> int:
    """The number of training frames for ``train_frames`` (a fraction in (0, 1) of the frames,
    or a count ``>= 2``), leaving at least one frame to test on unless it is 1.0 (all).

    Raises:
        ValueError: names ``train_frames`` and what was expected.
    """
    bad = ValueError(f"train_frames: expected a fraction in (0, 1] or a frame count in [2, "
                     f"{num_frames}], got {value!r}")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise bad
    if isinstance(value, float) and 0 < value <= 1:
        n = num_frames if value == 1.0 else int(round(value * num_frames))
    elif isinstance(value, int) and 2 <= value <= num_frames:
        n = value
    else:
        raise bad
    if n < 2:
        raise bad
    return n


def parameter_report(term) -> dict:
    """The learned parameters in readable units: per keypoint the offset (cm, in its bone
    frame), its change from the map's and the scale factor; per camera the scale (pixels at
    the detections' image scale); the calibration at its knots."""
    with torch.no_grad():
        off = term.offsets.double() * 100
        delta = (term.offsets - term.base_offsets).double() * 100
        kscale = term.log_keypoint_scale.exp().double()
        B = term.calibration_knots
        knots = torch.linspace(0, 1, B + 1, dtype=torch.float64)
        return {
            "keypoints": {n: {"joint": j, "frame": f, "offset_cm": [round(v, 2) for v in o],
                              "change_cm": [round(v, 2) for v in d],
                              "change_norm_cm": round(float(torch.tensor(d).norm()), 2),
                              "scale_factor": round(float(s), 3)}
                          for n, j, f, o, d, s in zip(term.kmap.names, term.kmap.joints,
                                                      term.kmap.frames, off.tolist(),
                                                      delta.tolist(), kscale.tolist())},
            "camera_scale_px": dict(zip(term.camera_names,
                                        [round(float(v), 3) for v in term.scale_px])),
            "calibration": {"confidence": [round(float(v), 3) for v in knots],
                            "weight": [round(float(v), 4)
                                       for v in term.calibrated(knots.to(term.calibration))]},
        }


def _fit_scores(term, runtime, det, tracked, held, theta0, n_train: int, iterations: int,
                min_confidence: float) -> dict:
    """Fit every frame with ``term`` (frame by frame) and score the fits: in the held-out view
    (``heldout``) or, without one, in the fitted views, on the test and train frames."""
    from torchmocap.evaluation import heldout_view_scores
    from torchmocap.learning.keypoints import track_poses

    t0 = time.perf_counter()
    theta = track_poses(term, runtime.skeleton, det, theta0, iterations)
    seconds = (time.perf_counter() - t0) / max(det.uv.shape[0], 1)
    rt = dataclasses.replace(runtime, keypoint_map=term.fitted_map())
    out: dict = {"seconds_per_frame": seconds}
    views = [(held, 0)] if held is not None else [(None, c) for c in
                                                  range(runtime.rig.num_cameras)]
    errs = []
    for seq, c in views:
        v = heldout_view_scores(seq if seq is not None else tracked, rt, theta, c,
                                min_confidence, silhouettes=False)
        errs.append(v.scores.errors_px / v.pixel_scale)
    e = torch.cat(errs, 1)
    for part, sl in (("test", slice(n_train, None)), ("train", slice(0, n_train))):
        x = e[sl]
        x = x[torch.isfinite(x)]
        out[part] = ({"median_px": float(x.median()), "mean_px": float(x.mean()),
                      "num_compared": int(x.numel())} if x.numel() else {})
    return out


def run(cfg: DictConfig, out: Path) -> dict:
    """Train as configured; returns the summary written to ``out/summary.json``."""
    from hydra.utils import get_object

    from torchmocap.assembly import Runtime, build, load_sequence
    from torchmocap.atomic import write_json_atomic
    from torchmocap.data import split_heldout
    from torchmocap.filters.tracking.tracker import check_seed, start_pose
    from torchmocap.learning.keypoints import (
        KeypointTrainSettings,
        stack_detections,
        train_keypoint_term,
    )
    from torchmocap.likelihoods import LearnedKeypointLikelihood

    seed = check_seed(cfg.seed)
    tr = cfg.training
    unknown = sorted(set(tr) - {f.name for f in dataclasses.fields(KeypointTrainSettings)})
    if unknown:
        raise ValueError(f"training: unknown settings {unknown} (known: "
                         f"{[f.name for f in dataclasses.fields(KeypointTrainSettings)]})")
    settings = KeypointTrainSettings(**OmegaConf.to_container(tr, resolve=True))
    settings.check()  # settings errors before any loading
    train_frame_count(cfg.train_frames, sys.maxsize)  # its type and range, before loading
    target = get_object(str(cfg.term._target_))
    if not (isinstance(target, type) and issubclass(target, LearnedKeypointLikelihood)):
        raise ValueError(f"term: {cfg.term._target_} is not a LearnedKeypointLikelihood "
                         "(term=keypoints_learned)")
    t0 = time.perf_counter()
    seq = load_sequence(cfg, min_frames=2)
    tracked, held = split_heldout(seq)
    if tracked.joints2d is None:
        raise ValueError(f"data: {cfg.data.get('path')} has no 2D keypoint detections to train "
                         "the keypoint term on (keypoints.source)")
    runtime = Runtime.from_sequence(tracked)
    term = build(cfg.term, runtime, _path="term")
    hand = build(OmegaConf.merge(cfg.term, {"weights": None, "learn": False}), runtime,
                 _path="term")
    det = stack_detections(term, tracked)
    T = det.uv.shape[0]
    n_train = train_frame_count(cfg.train_frames, T)
    theta0 = start_pose(tracked).to(runtime.skeleton.offsets.dtype)
    t_data = time.perf_counter() - t0
    torch.manual_seed(int(seed))
    progress = (lambda m: print(f"torchmocap-train: {m}", flush=True)) if cfg.progress else None
    t1 = time.perf_counter()
    result = train_keypoint_term(term, runtime.skeleton, det.frames(0, n_train), theta0,
                                 settings, progress)
    t_train = time.perf_counter() - t1
    info = {"data": str(cfg.data.get("path")), "cameras": list(runtime.rig.names),
            "heldout_camera": None if held is None else held.rig.names[0],
            "train_frames": n_train, "frames": T, "seed": int(seed),
            "settings": result["settings"], "history": result["history"]}
    weights = term.save_weights(out / "keypoints.pt", training=info)
    if cfg.get("export"):
        term.save_weights(Path(str(cfg.export)), training=info)
    scores = {}
    if cfg.evaluate:
        mc = float(cfg.evaluation.get("min_confidence", 0.3))
        for name, t in (("hand_set", hand), ("learned", term)):
            scores[name] = _fit_scores(t, runtime, det, tracked, held, theta0, n_train,
                                       settings.pose_iterations, mc)
    summary = {"term": type(term).__name__, **info, "detections": result["detections"],
               "seconds_data": t_data, "seconds_training": t_train, "weights": str(weights),
               "scored_in": "held-out camera" if held is not None else "training cameras",
               "scores": scores, "parameters": parameter_report(term)}
    write_json_atomic(summary, out / "summary.json")
    lines = [f"{n_train} of {T} frames of {list(runtime.rig.names)} in {t_train:.0f} s; "
             f"weights {weights}"]
    for name, s in scores.items():
        te = s.get("test") or {}
        lines.append(f"{name}: test frames {te.get('median_px', float('nan')):.1f} px median, "
                     f"{te.get('mean_px', float('nan')):.1f} mean ({summary['scored_in']})")
    summary["report"] = "; ".join(lines)
    return summary
