"""One call that scores a finished track: :func:`evaluate_track` (what ``torchmocap-track``
writes into ``metrics.json`` and ``track.npz`` besides the run's settings)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import torch

from torchmocap.evaluation.consistency import track_consistency
from torchmocap.evaluation.diagnostics import (
    hypothesis_arrays,
    smoother_report,
    summarize_diagnostics,
)
from torchmocap.evaluation.heldout import heldout_view_scores
from torchmocap.evaluation.truth import (
    energy_below_truth,
    error_means,
    held_dofs,
    hypothesis_errors,
    marker_error,
    track_errors,
)
from torchmocap.evaluation.views import reprojection_error, silhouette_agreement
from torchmocap.evaluation.warnings import EvaluationWarning
from torchmocap.likelihoods.silhouette import check_fit_iou

__all__ = ["TrackEvaluation", "evaluate_track", "tracked_keypoint_map"]

#: sequence meta entries reported beside the scores (a recording's hull top, subject scale,
#: subject fit and its views' agreement)
META_KEYS = ("body_height", "calibration_refinement", "hull_top_m", "phenotype", "skeleton_scale",
             "source", "subject_fit", "view_consistency")


@dataclass
class TrackEvaluation:
    """The scores of a track.

    Attributes:
        metrics: JSON-ready scores (see :func:`evaluate_track`).
        arrays: per-frame arrays for ``track.npz``: ``theta (T, D)``, ``dof_names``, with
            ground truth ``theta_gt``, ``orientation_error_deg (T-1, B)``, ``mpjpe_mm (T-1,)``;
            with a smoother ``theta_filtered``; with hypotheses ``hypotheses (T, K, D)``,
            ``hypothesis_weights``, ``hypothesis_energy``.
    """

    metrics: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, Any] = field(default_factory=dict)


def tracked_keypoint_map(tracker):
    """The keypoint map of the tracker's keypoint term with its current offsets
    (:meth:`~torchmocap.likelihoods.KeypointLikelihood.fitted_map`: a learned term's differ from
    the subject's map), or None when its likelihood has no keypoint term."""
    from torchmocap.likelihoods import KeypointLikelihood

    likelihood = getattr(tracker, "likelihood", None)
    if not isinstance(likelihood, torch.nn.Module):
        return None
    terms = [m for m in likelihood.modules() if isinstance(m, KeypointLikelihood)]
    return terms[0].fitted_map() if len(terms) == 1 else None


def evaluate_track(seq, runtime, tracker, track, energy_vs_truth: bool = False,
                   heldout=None, min_confidence: float = 0.3) -> TrackEvaluation:
    """Score ``track`` (a :class:`~torchmocap.filters.Track` of ``seq`` by ``tracker``).

    Args:
        seq: the tracked :class:`~torchmocap.data.Sequence`.
        runtime: the :class:`~torchmocap.assembly.Runtime` the tracker was built with (its
            skeleton, body and rig score the track).
        tracker: the :class:`~torchmocap.filters.Tracker` (its likelihood for
            ``energy_vs_truth``).
        track: the finished track.
        energy_vs_truth: also report the fraction of frames whose estimate has a lower energy
            than the truth (one energy evaluation per frame).
        heldout: the camera held out of ``seq`` as a one-camera sequence
            (:func:`~torchmocap.data.split_heldout`), or None.
        min_confidence: detections above it are compared in the views' scores.

    Returns:
        :class:`TrackEvaluation`. ``metrics``: the diagnostics summary
        (:func:`~torchmocap.evaluation.summarize_diagnostics`); with a smoother its report
        (``smoother``); with ground truth the errors of :func:`track_errors` (validation bones,
        orientation error, MPJPE, root-aligned MPJPE), ``held_dofs``, ``hold_first_pose`` (the
        errors of a do-nothing tracker that keeps the first pose), with a smoother
        ``filtered`` (the tracker's own errors) and each chain stage's errors, with skin
        markers ``marker_error_mm``, with hypotheses ``hypotheses``, and on request
        ``estimate_energy_below_truth``; without ground truth ``silhouette_iou``; with 2D
        joints ``reprojection_px``; the sequence's ``hull_top_m``, ``skeleton_scale``,
        ``source``, ``subject_fit`` and ``view_consistency`` when it has them; without ground
        truth, over 3 frames or more, ``consistency``
        (:func:`~torchmocap.evaluation.track_consistency`: bone-length CV and jitter of the
        mapped keypoints, or of the joints); with a keypoint map, the track's
        scores in each tracked view's detections (``tracked_views``: median px of the full-size
        images, PCK) and with ``heldout`` those in the held-out view (``heldout``:
        :meth:`~torchmocap.evaluation.HeldOutView.summary`, with the first pose held beside
        and the keypoint mapping — the keypoints are those of the tracker's keypoint term,
        :func:`tracked_keypoint_map`; ``track.npz`` gets ``heldout_errors_px (T, K')`` and
        ``heldout_silhouette_iou (T,)``). Warnings:
        :class:`~torchmocap.evaluation.EvaluationWarning`.
    """
    sk = runtime.skeleton
    kmap = tracked_keypoint_map(tracker)
    if kmap is not None:  # the model points the tracker scored (a learned term's offsets)
        runtime = dataclasses.replace(runtime, keypoint_map=kmap)
    metrics: dict[str, Any] = dict(summarize_diagnostics(track.infos))
    arrays: dict[str, Any] = {"theta": track.theta.numpy(), "dof_names": _dof_names(sk),
                              **hypothesis_arrays(track.infos, sk.num_dofs)}
    smoothing = track.smoother
    if track.filtered is not None:  # theta is smoothed; the filter's own estimates beside it
        arrays["theta_filtered"] = track.filtered.numpy()
        if smoothing:
            metrics["smoother"] = smoother_report(smoothing)
    if seq.ground_truth is not None:
        errors = track_errors(seq, sk, track.theta)
        metrics.update(errors.pop("summary"))
        arrays.update({k: v.numpy() for k, v in errors.items()})
        held = held_dofs(seq, sk, track.theta)
        if held:
            metrics["held_dofs"] = held
        # the do-nothing tracker: the first frame's pose (every tracker's start) held throughout
        metrics["hold_first_pose"] = error_means(
            track_errors(seq, sk, track.theta[:1].expand_as(track.theta))["summary"])
        if track.filtered is not None:
            metrics["filtered"] = error_means(track_errors(seq, sk, track.filtered)["summary"])
            # a chain of smoothers: the errors after each stage (an ablation in one run); the
            # last stage's are the top-level ones
            stages = (smoothing or {}).get("stages") or []
            for k, rep in enumerate(stages):
                if not (isinstance(rep, dict) and isinstance(rep.get("theta"), torch.Tensor)):
                    continue
                e = (metrics if k == len(stages) - 1
                     else track_errors(seq, sk, rep["theta"].cpu())["summary"])
                metrics["smoother"]["stages"][k]["errors"] = error_means(e)
        if seq.ground_truth.markers is not None:
            metrics["marker_error_mm"] = marker_error(seq, runtime.body, sk, track.theta)
            if track.filtered is not None:
                metrics["filtered"]["marker_error_mm"] = marker_error(
                    seq, runtime.body, sk, track.filtered)["mean"]
        hyp = hypothesis_errors(seq, sk, track.infos)
        if hyp:
            metrics["hypotheses"] = hyp
        if energy_vs_truth:
            metrics["estimate_energy_below_truth"] = energy_below_truth(tracker, seq,
                                                                        track.theta)
    else:
        metrics["silhouette_iou"] = iou = silhouette_agreement(seq, runtime.body, runtime.rig,
                                                               track.theta)
        if iou and iou["mean_over_frames"] is not None:  # no truth: an IoU far below a
            # fit's is the sign of wrong masks or cameras
            check_fit_iou(iou["mean_over_frames"], "silhouette_iou", EvaluationWarning)
    if seq.joints2d is not None and runtime.rig is not None:
        metrics["reprojection_px"] = reprojection_error(seq, sk, runtime.rig, track.theta)
        if runtime.keypoint_map is not None:
            metrics["tracked_views"] = {}
            for c, name in enumerate(seq.rig.names):
                v = heldout_view_scores(seq, runtime, track.theta, c, min_confidence,
                                        silhouettes=False).summary()
                metrics["tracked_views"][name] = {k: v[k] for k in ("median_px", "pck_05",
                                                                    "pck_10", "num_compared")}
    if seq.ground_truth is None and track.theta.shape[0] >= 3:
        metrics["consistency"] = track_consistency(sk, track.theta, seq.fps,
                                                   runtime.keypoint_map)
    if heldout is not None:
        view = heldout_view_scores(heldout, runtime, track.theta, 0, min_confidence)
        metrics["heldout"] = view.summary()
        if view.scores is not None:
            arrays["heldout_errors_px"] = (view.scores.errors_px / view.pixel_scale).numpy()
        if view.silhouette_iou is not None:
            arrays["heldout_silhouette_iou"] = view.silhouette_iou.numpy()
    for k in META_KEYS:
        if (v := getattr(seq.meta, k)) is not None:
            metrics[k] = v
    fit = metrics.get("body_fit") or {}
    if fit.get("height") is not None and seq.meta.body_height is not None:
        fit["height_error_m"] = round(fit["height"] - seq.meta.body_height, 5)
    return TrackEvaluation(metrics=metrics, arrays=arrays)


def _dof_names(skeleton):
    import numpy as np

    return np.array(skeleton.dof_names)
