"""torchmocap.filters: trackers and the components they are built from.

* :mod:`~torchmocap.filters.tracking` — the :class:`Tracker` loop, its typed records
  (:class:`Track`, :class:`FrameInfo`, :class:`TrackState`), estimators, the pose predictor, the
  first frame's body fit, batched seeds;
* :mod:`~torchmocap.filters.inference` — per-frame inference modules: annealing, local
  descent, SIR, mixture density propagation;
* :mod:`~torchmocap.filters.smoothing` — offline smoothers of a finished track;
* :mod:`~torchmocap.filters.optim` — the functional core on generic particle tensors
  ``(P, D)``: annealed optimisation, schedules, resampling, SIR steps, local minimisation, the
  temporal prior, rotation coordinates.

This namespace gathers the components a config chooses by ``_target_`` and a user composes;
the functions of the core are in :mod:`torchmocap.filters.optim`.
"""

from torchmocap.filters.inference import (
    AnnealedInference,
    Inference,
    InferenceResult,
    LocalInference,
    MixtureInference,
    ShrinkingDiffusion,
    SIRInference,
    SpreadDiffusion,
)
from torchmocap.filters.optim import (
    ESSSchedule,
    GeometricSchedule,
    KeepRedrawResampler,
    MultinomialResampler,
    PolynomialSchedule,
    Resampler,
    ResidualResampler,
    StratifiedResampler,
    SystematicResampler,
    TemporalPrior,
)
from torchmocap.filters.smoothing import (
    KalmanSmoother,
    Smoother,
    SmootherChain,
    ViterbiSmoother,
)
from torchmocap.filters.tracking import (
    AnnyBodyFit,
    BatchGroup,
    BestParticleEstimator,
    BodyFit,
    CheckpointError,
    Estimator,
    FrameInfo,
    ManifoldMeanEstimator,
    MissingObservationError,
    PosePredictor,
    SilhouetteBodyFit,
    TemporalMapEstimator,
    Track,
    Tracker,
    TrackState,
    WeightedMeanEstimator,
    track_groups,
    track_seeds,
)

__all__ = [
    "AnnealedInference",
    "BatchGroup",
    "BestParticleEstimator",
    "CheckpointError",
    "ESSSchedule",
    "Estimator",
    "FrameInfo",
    "GeometricSchedule",
    "Inference",
    "InferenceResult",
    "KalmanSmoother",
    "KeepRedrawResampler",
    "LocalInference",
    "ManifoldMeanEstimator",
    "MissingObservationError",
    "MixtureInference",
    "MultinomialResampler",
    "PolynomialSchedule",
    "PosePredictor",
    "Resampler",
    "ResidualResampler",
    "SIRInference",
    "ShrinkingDiffusion",
    "BodyFit",
    "SilhouetteBodyFit",
    "AnnyBodyFit",
    "Smoother",
    "SmootherChain",
    "SpreadDiffusion",
    "StratifiedResampler",
    "SystematicResampler",
    "TemporalMapEstimator",
    "TemporalPrior",
    "Track",
    "TrackState",
    "Tracker",
    "ViterbiSmoother",
    "WeightedMeanEstimator",
    "track_groups",
    "track_seeds",
]
