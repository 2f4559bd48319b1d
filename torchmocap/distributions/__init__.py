"""Distributions for sensor noise: von Mises–Fisher on spheres, tangent Gaussians on SO(3), and
the Gaussian-on-joint-parameters baseline of Pons-Moll et al., and the truncated normal angular
prior of Hauberg & Pedersen (torch.distributions API, explicit ``torch.Generator`` everywhere)."""

from torchmocap.distributions.bessel import (
    bessel_iv_ratio,
    log_bessel_iv,
    log_bessel_iv_scaled_power,
    log_bessel_ive_scaled_power,
)
from torchmocap.distributions.covariance_scaled import (
    CovarianceScaledSampler,
    bhattacharyya_distance,
    covariance_scaled_sample,
    hessian_to_covariance,
    mixture_covariance_scaled_sample,
    spherical_covariance,
)
from torchmocap.distributions.tangent_gaussian import (
    ParameterGaussianNoise,
    TangentGaussianSO3,
    add_parameter_noise,
)
from torchmocap.distributions.truncated_normal import TruncatedNormal, log_normal_mass
from torchmocap.distributions.von_mises_fisher import (
    VonMisesFisher,
    kappa_to_angle,
    kappa_to_tangent_std,
    sphere,
    vmf_kappa_one_minus_a,
    vmf_log_normalizer,
    vmf_mean_resultant_length,
)

__all__ = [
    "CovarianceScaledSampler",
    "ParameterGaussianNoise",
    "TangentGaussianSO3",
    "TruncatedNormal",
    "VonMisesFisher",
    "add_parameter_noise",
    "bessel_iv_ratio",
    "bhattacharyya_distance",
    "covariance_scaled_sample",
    "hessian_to_covariance",
    "kappa_to_angle",
    "kappa_to_tangent_std",
    "log_bessel_iv",
    "log_bessel_iv_scaled_power",
    "log_bessel_ive_scaled_power",
    "log_normal_mass",
    "mixture_covariance_scaled_sample",
    "sphere",
    "spherical_covariance",
    "vmf_kappa_one_minus_a",
    "vmf_log_normalizer",
    "vmf_mean_resultant_length",
]
