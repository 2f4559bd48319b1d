"""Per-frame inference modules (``inference(energy, proposal, estimator, context, num,
generator) -> InferenceResult``): annealed particle optimisation, local descent, sequential
importance resampling and mixture density propagation."""

from torchmocap.filters.inference.annealed import (
    AnnealedInference,
    ShrinkingDiffusion,
    SpreadDiffusion,
)
from torchmocap.filters.inference.base import Inference, InferenceResult
from torchmocap.filters.inference.local import LocalInference
from torchmocap.filters.inference.mixture import MixtureInference, gauss_newton_function
from torchmocap.filters.inference.sir import SIRInference

__all__ = [
    "AnnealedInference",
    "Inference",
    "InferenceResult",
    "LocalInference",
    "MixtureInference",
    "SIRInference",
    "ShrinkingDiffusion",
    "SpreadDiffusion",
    "gauss_newton_function",
]
