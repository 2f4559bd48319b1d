"""Offline smoothers of a finished track (``tracker.smoother``): the Viterbi sequence of a
multi-hypothesis tracker's modes, the constant-velocity Kalman (RTS) smoother, and chains of
them."""

from torchmocap.filters.smoothing.base import Smoother, SmootherChain
from torchmocap.filters.smoothing.kalman import (
    KalmanSmoother,
    cv_kalman_smoother,
    fit_cv_noise,
    unwrap_angles,
)
from torchmocap.filters.smoothing.viterbi import ViterbiSmoother, viterbi_path

__all__ = [
    "KalmanSmoother",
    "Smoother",
    "SmootherChain",
    "ViterbiSmoother",
    "cv_kalman_smoother",
    "fit_cv_noise",
    "unwrap_angles",
    "viterbi_path",
]
