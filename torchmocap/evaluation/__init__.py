"""torchmocap.evaluation: what a run is scored by — with ground truth (orientation error,
MPJPE, held DoFs, hypotheses, marker error) or without it (the views' detections and masks) —
and the summaries of a track's per-frame diagnostics. Library functions that the command line
and the experiments both call; :func:`evaluate_track` scores a finished track in one call.
"""

from torchmocap.evaluation.diagnostics import (
    hypothesis_arrays,
    smoother_report,
    summarize_diagnostics,
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
    "VALIDATION_BONES_FALLBACK",
    "EvaluationWarning",
    "TrackEvaluation",
    "energy_below_truth",
    "error_means",
    "evaluate_track",
    "held_dofs",
    "hypothesis_arrays",
    "hypothesis_errors",
    "marker_error",
    "reprojection_error",
    "root_joint",
    "silhouette_agreement",
    "smoother_report",
    "summarize_diagnostics",
    "track_errors",
    "validation_bones",
]
