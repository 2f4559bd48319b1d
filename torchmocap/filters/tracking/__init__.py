"""The frame-by-frame :class:`Tracker` (the loop that composes a predictor, a proposal, a
likelihood, an inference module and an estimator), its typed state and records, the estimators
and the pose predictor, the first frame's body fit, and several tracks in one batch."""

from torchmocap.filters.tracking.batched import BatchGroup, Lockstep, track_groups, track_seeds
from torchmocap.filters.tracking.body_fit import BodyFit, SilhouetteBodyFit
from torchmocap.filters.tracking.estimators import (
    BestParticleEstimator,
    Estimator,
    ManifoldMeanEstimator,
    TemporalMapEstimator,
    WeightedMeanEstimator,
)
from torchmocap.filters.tracking.prediction import PosePredictor, predict_ar3
from torchmocap.filters.tracking.shape_fit import AnnyBodyFit
from torchmocap.filters.tracking.state import FrameInfo, Track, TrackState
from torchmocap.filters.tracking.tracker import (
    CheckpointError,
    MissingObservationError,
    Tracker,
    initial_pose,
    start_pose,
)

__all__ = [
    "BatchGroup",
    "BestParticleEstimator",
    "CheckpointError",
    "Estimator",
    "FrameInfo",
    "Lockstep",
    "ManifoldMeanEstimator",
    "MissingObservationError",
    "PosePredictor",
    "BodyFit",
    "SilhouetteBodyFit",
    "AnnyBodyFit",
    "TemporalMapEstimator",
    "Track",
    "TrackState",
    "Tracker",
    "WeightedMeanEstimator",
    "initial_pose",
    "start_pose",
    "predict_ar3",
    "track_groups",
    "track_seeds",
]
