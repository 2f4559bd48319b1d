"""torchmocap.proposals: ``sample(context, num, generator) -> Proposed`` samplers of poses, and
the sensor-noise models of manifold sampling."""

from torchmocap.proposals.angular import UPPER_BODY, AngularPriorProposal, free_dofs
from torchmocap.proposals.base import (
    GaussianDiffusionProposal,
    PreviousFrame,
    Proposal,
    ProposalContext,
    Proposed,
    select_ancestors,
)
from torchmocap.proposals.bounds import BOUNDARIES, bound_particles
from torchmocap.proposals.covariance_scaled import (
    CovarianceScaledProposal,
    context_covariances,
    mode_set,
)
from torchmocap.proposals.jumps import (
    JumpChain,
    KinematicJumpProposal,
    KinematicJumps,
    LimbFlips,
    chain_votes,
    kinematic_jumps,
    limb_flips,
    parse_chain,
    select_chains,
)
from torchmocap.proposals.manifold import ManifoldProposal
from torchmocap.proposals.noise import (
    NoSensorNoise,
    PassiveGaussianNoise,
    SensorNoise,
    TangentGaussianNoise,
    VonMisesFisherNoise,
)
from torchmocap.proposals.rejection import RejectionProposal, SensorAngleCriterion
from torchmocap.proposals.spatial import (
    InSilhouette,
    JointCriterion,
    NearPointCloud,
    PoseInSilhouette,
    SpatialPriorProposal,
    tracked_joints,
)
from torchmocap.proposals.uncovered import (
    UncoveredLimbProposal,
    draw_limb_targets,
    foreground_points,
    unexplained_distance,
)

__all__ = [
    "AngularPriorProposal",
    "BOUNDARIES",
    "CovarianceScaledProposal",
    "PreviousFrame",
    "GaussianDiffusionProposal",
    "InSilhouette",
    "JointCriterion",
    "JumpChain",
    "KinematicJumpProposal",
    "KinematicJumps",
    "LimbFlips",
    "ManifoldProposal",
    "NearPointCloud",
    "NoSensorNoise",
    "PassiveGaussianNoise",
    "PoseInSilhouette",
    "Proposal",
    "ProposalContext",
    "Proposed",
    "RejectionProposal",
    "SensorAngleCriterion",
    "SensorNoise",
    "SpatialPriorProposal",
    "TangentGaussianNoise",
    "UPPER_BODY",
    "UncoveredLimbProposal",
    "VonMisesFisherNoise",
    "bound_particles",
    "chain_votes",
    "context_covariances",
    "draw_limb_targets",
    "foreground_points",
    "free_dofs",
    "kinematic_jumps",
    "limb_flips",
    "mode_set",
    "parse_chain",
    "select_ancestors",
    "select_chains",
    "tracked_joints",
    "unexplained_distance",
]
