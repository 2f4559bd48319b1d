"""Training learned likelihood terms: data (clips, negatives), objectives (ranking, unrolled
inference with stop-gradient resampling), checkpoints and the training loop behind
``torchmocap-train``."""

from torchmocap.learning.checkpoints import load_checkpoint, save_checkpoint
from torchmocap.learning.data import (
    ClipData,
    NegativeSettings,
    TrainingFrame,
    build_clip_data,
    load_clip_set,
    pose_errors,
)
from torchmocap.learning.objectives import (
    joint_error,
    ranking_loss,
    stop_gradient_resample,
    unrolled_annealing,
    unrolled_descent,
)

__all__ = [
    "ClipData",
    "NegativeSettings",
    "TrainingFrame",
    "build_clip_data",
    "joint_error",
    "load_checkpoint",
    "load_clip_set",
    "pose_errors",
    "ranking_loss",
    "save_checkpoint",
    "stop_gradient_resample",
    "unrolled_annealing",
    "unrolled_descent",
]
