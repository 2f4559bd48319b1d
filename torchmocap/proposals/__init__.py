"""torchmocap.proposals: ``sample(context, num, generator) -> Proposed`` samplers of poses."""

from torchmocap.proposals.base import (
    GaussianDiffusionProposal,
    Proposal,
    ProposalContext,
    Proposed,
    select_ancestors,
)
from torchmocap.proposals.manifold import NOISE_MODELS, ManifoldProposal, perturb_sensors
from torchmocap.proposals.rejection import RejectionProposal, SensorAngleCriterion

__all__ = [
    "NOISE_MODELS",
    "GaussianDiffusionProposal",
    "ManifoldProposal",
    "Proposal",
    "ProposalContext",
    "Proposed",
    "RejectionProposal",
    "SensorAngleCriterion",
    "perturb_sensors",
    "select_ancestors",
]
