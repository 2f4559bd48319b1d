"""The functional core of the filters: algorithms on generic particle tensors ``(P, D)`` —
annealed particle optimisation (:func:`anneal`), its schedules, resampling, SIR steps, local
minimisation, energy derivatives, batched Levenberg–Marquardt, the modes of a mixture, the
Gaussian temporal prior and rotation coordinates of pose vectors. Nothing here
knows a skeleton, a likelihood or a frame; the inference modules
(:mod:`torchmocap.filters.inference`) build on them.
"""

from torchmocap.filters.optim.anneal import (
    AnnealingResult,
    CovarianceDiffusion,
    GeometricDiffusion,
    anneal,
    bound_particles,
    default_diffusion,
    rotation_mean_fn,
    weighted_mean,
)
from torchmocap.filters.optim.derivatives import energy_derivatives
from torchmocap.filters.optim.levenberg import levenberg_marquardt
from torchmocap.filters.optim.local import LocalResult, minimise_local
from torchmocap.filters.optim.modes import bhattacharyya_reweight, distinct_minima
from torchmocap.filters.optim.resampling import (
    KeepRedrawResampler,
    MultinomialResampler,
    Resampler,
    ResidualResampler,
    StratifiedResampler,
    SystematicResampler,
    as_resampler,
    counts_to_indices,
    effective_sample_size,
    ess_fraction,
    gather_particles,
    keep_redraw_resample,
    multinomial_resample,
    normalize_log_weights,
    offspring_counts,
    residual_resample,
    stratified_resample,
    systematic_resample,
)
from torchmocap.filters.optim.rotations import (
    RotationGroup,
    angles_from_matrix,
    euler_matrix,
    skeleton_rotation_groups,
)
from torchmocap.filters.optim.schedules import (
    BetaSolution,
    ESSSchedule,
    GeometricSchedule,
    PolynomialSchedule,
    annealing_log_weights,
    as_schedule,
    ess_fraction_at_beta,
    ess_target_beta,
)
from torchmocap.filters.optim.sir import SIRResult, SIRStep, sir_filter, sir_step
from torchmocap.filters.optim.temporal_prior import TemporalPrior, temporal_prior_precision

__all__ = [
    "AnnealingResult",
    "BetaSolution",
    "CovarianceDiffusion",
    "ESSSchedule",
    "GeometricDiffusion",
    "GeometricSchedule",
    "KeepRedrawResampler",
    "LocalResult",
    "MultinomialResampler",
    "PolynomialSchedule",
    "Resampler",
    "ResidualResampler",
    "RotationGroup",
    "SIRResult",
    "SIRStep",
    "StratifiedResampler",
    "SystematicResampler",
    "TemporalPrior",
    "angles_from_matrix",
    "anneal",
    "annealing_log_weights",
    "as_resampler",
    "as_schedule",
    "bhattacharyya_reweight",
    "bound_particles",
    "counts_to_indices",
    "default_diffusion",
    "distinct_minima",
    "effective_sample_size",
    "energy_derivatives",
    "ess_fraction",
    "ess_fraction_at_beta",
    "ess_target_beta",
    "euler_matrix",
    "gather_particles",
    "keep_redraw_resample",
    "levenberg_marquardt",
    "minimise_local",
    "multinomial_resample",
    "normalize_log_weights",
    "offspring_counts",
    "residual_resample",
    "rotation_mean_fn",
    "sir_filter",
    "sir_step",
    "skeleton_rotation_groups",
    "stratified_resample",
    "systematic_resample",
    "temporal_prior_precision",
    "weighted_mean",
]
