"""torchmocap.evaluation: what a run is scored by — with ground truth (orientation error,
MPJPE, held DoFs, hypotheses, marker error) or without it (a held-out camera's detections,
bone-length constancy, jitter, silhouette agreement). Library functions that the command line
and the experiments both call.

Without ground truth: :func:`reprojection_scores` (pixel error and PCK of a reconstruction in
one view's detections) and :func:`leave_one_camera_out` (:mod:`~torchmocap.evaluation.heldout`);
:func:`bone_length_cv` and :func:`jitter` (:mod:`~torchmocap.evaluation.consistency`).
"""

from torchmocap.evaluation.consistency import BoneLengthCV, Jitter, bone_length_cv, jitter
from torchmocap.evaluation.heldout import (
    ReprojectionScores,
    leave_one_camera_out,
    reprojection_scores,
)

__all__ = [
    "BoneLengthCV",
    "Jitter",
    "ReprojectionScores",
    "bone_length_cv",
    "jitter",
    "leave_one_camera_out",
    "reprojection_scores",
]
