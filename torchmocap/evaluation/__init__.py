"""torchmocap.evaluation: what a run is scored by — with ground truth (orientation error,
MPJPE, held DoFs, hypotheses, marker error) or without it (a held-out camera's detections,
bone-length constancy, jitter, silhouette agreement) — and the summaries of a track's per-frame
diagnostics. Library functions that the command line and the experiments both call;
:func:`evaluate_track` scores a finished track in one call.

Without ground truth: :func:`reprojection_scores` (pixel error and PCK of a reconstruction in
one view's detections), :func:`leave_one_camera_out` and :func:`heldout_view_scores` (a track in
a camera it did not see) (:mod:`~torchmocap.evaluation.heldout`); :func:`bone_length_cv`,
:func:`jitter` and :func:`track_consistency` (:mod:`~torchmocap.evaluation.consistency`).
"""

from torchmocap.evaluation.consistency import (
    LIMB_KEYPOINTS,
    BoneLengthCV,
    Jitter,
    bone_length_cv,
    jitter,
    track_consistency,
)
from torchmocap.evaluation.diagnostics import (
    hypothesis_arrays,
    smoother_report,
    summarize_diagnostics,
)
from torchmocap.evaluation.heldout import (
    HeldOutView,
    ReprojectionScores,
    heldout_view_scores,
    leave_one_camera_out,
    reprojection_scores,
)
from torchmocap.evaluation.track import TrackEvaluation, evaluate_track
from torchmocap.evaluation.truth import (
    VALIDATION_BONES_FALLBACK,
    energy_below_truth,
    error_means,
    held_dofs,
    hypothesis_errors,
    marker_error,
    root_joint,
    track_errors,
    validation_bones,
)
from torchmocap.evaluation.views import reprojection_error, silhouette_agreement
from torchmocap.evaluation.warnings import EvaluationWarning

__all__ = [
    "LIMB_KEYPOINTS",
    "VALIDATION_BONES_FALLBACK",
    "BoneLengthCV",
    "EvaluationWarning",
    "HeldOutView",
    "Jitter",
    "ReprojectionScores",
    "TrackEvaluation",
    "bone_length_cv",
    "energy_below_truth",
    "error_means",
    "evaluate_track",
    "held_dofs",
    "heldout_view_scores",
    "hypothesis_arrays",
    "hypothesis_errors",
    "jitter",
    "leave_one_camera_out",
    "marker_error",
    "reprojection_error",
    "reprojection_scores",
    "root_joint",
    "silhouette_agreement",
    "smoother_report",
    "summarize_diagnostics",
    "track_consistency",
    "track_errors",
    "validation_bones",
]
