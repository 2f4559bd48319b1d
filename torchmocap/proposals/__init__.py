"""torchmocap.proposals: ``sample(context, num, generator) -> Proposed`` samplers of poses, and
the sensor-noise models of manifold sampling."""

from torchmocap.proposals.base import (
    GaussianDiffusionProposal,
    Proposal,
    ProposalContext,
    Proposed,
    select_ancestors,
)
from torchmocap.proposals.bounds import BOUNDARIES, bound_particles
from torchmocap.proposals.manifold import ManifoldProposal
from torchmocap.proposals.noise import (
    NoSensorNoise,
    PassiveGaussianNoise,
    SensorNoise,
    TangentGaussianNoise,
    VonMisesFisherNoise,
)
from torchmocap.proposals.rejection import RejectionProposal, SensorAngleCriterion

__all__ = [
    "BOUNDARIES",
    "GaussianDiffusionProposal",
    "ManifoldProposal",
    "NoSensorNoise",
    "PassiveGaussianNoise",
    "Proposal",
    "ProposalContext",
    "Proposed",
    "RejectionProposal",
    "SensorAngleCriterion",
    "SensorNoise",
    "TangentGaussianNoise",
    "VonMisesFisherNoise",
    "bound_particles",
    "select_ancestors",
]
