"""Sensor-noise models of manifold sampling (Pons-Moll et al. 2010, §4.2, Table 2, Fig. 10).

A :class:`SensorNoise` perturbs what :class:`~torchmocap.proposals.ManifoldProposal` feeds to
``g^{-1}``: either the sensor orientations (right-multiplied noise rotations ``R_TS R_w``, eq. 16,
fused into the inverse kinematics) or the resulting passive joint parameters. The models of the
paper's ablation, each one config option of the ``noise`` group:

* :class:`NoSensorNoise` — the measured orientations as they are (paper: 26.8°);
* :class:`PassiveGaussianNoise` — the paper's GN baseline: Gaussian noise on the *passive joint
  parameters* after ``g^{-1}`` (13°; anisotropic near gimbal lock, Fig. 5);
* :class:`VonMisesFisherNoise` — ``q~ = q ∘ q_w``, ``q_w ~ vMF((1,0,0,0), κ)`` on S³ (7.3° at
  κ = 1000);
* :class:`TangentGaussianNoise` — ``R~ = R exp(hat(v))``, ``v ~ N(0, σ² I)`` (isotropic;
  statistically equivalent to vMF at ``σ = 2/√κ``).

All draws use the caller's ``torch.Generator``. Shapes: ``P`` particles, ``S`` sensors.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from torchmocap.distributions.tangent_gaussian import add_parameter_noise
from torchmocap.distributions.von_mises_fisher import VonMisesFisher, kappa_to_tangent_std
from torchmocap.geometry import axis_angle_to_quaternion

__all__ = [
    "NoSensorNoise",
    "PassiveGaussianNoise",
    "SensorNoise",
    "TangentGaussianNoise",
    "VonMisesFisherNoise",
]


def _positive(name: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
    return float(v)


class SensorNoise(nn.Module):
    """Base class: no noise. Subclasses override one or both hooks."""

    def sensor_noise(self, num: int, num_sensors: int, *, dtype: torch.dtype,
                     device: torch.device | None = None,
                     generator: torch.Generator | None = None) -> torch.Tensor | None:
        """Unit quaternions ``(num, S, 4)`` (w, x, y, z) right-multiplied onto the sensor
        orientations before ``g^{-1}``, or ``None`` for none."""
        return None

    def perturb_passive(self, theta: torch.Tensor, passive_index: torch.Tensor,
                        generator: torch.Generator | None = None) -> torch.Tensor:
        """Poses ``(P, D)`` after ``g^{-1}`` with noise on the passive coordinates
        ``passive_index`` (default: unchanged)."""
        return theta

    def sensor_rotations(self, R: torch.Tensor, num: int,
                         generator: torch.Generator | None = None) -> torch.Tensor:
        """``num`` noisy copies ``(num, S, 3, 3)`` of sensor orientations ``R (S, 3, 3)``."""
        from torchmocap.geometry import quaternion_to_matrix

        S = R.shape[-3]
        q = self.sensor_noise(num, S, dtype=R.dtype, device=R.device, generator=generator)
        R = R.expand(num, S, 3, 3)
        return R if q is None else R @ quaternion_to_matrix(q)


class NoSensorNoise(SensorNoise):
    """The measured sensor orientations as they are."""


class VonMisesFisherNoise(SensorNoise):
    """vMF noise on S³ around the identity quaternion (eq. 16).

    Args:
        kappa: concentration (1000 in the paper: median 5.6°, 95th percentile 10.1°).
    """

    def __init__(self, kappa: float = 1000.0) -> None:
        super().__init__()
        self.kappa = _positive("kappa", kappa)
        self._dist: dict = {}

    def _distribution(self, dtype, device) -> VonMisesFisher:
        key = (dtype, str(device))
        d = self._dist.get(key)
        if d is None:
            e1 = torch.zeros(4, dtype=dtype, device=device)
            e1[0] = 1
            d = VonMisesFisher(e1, torch.tensor(self.kappa, dtype=dtype, device=device),
                               validate_args=False)
            self._dist[key] = d
        return d

    def sensor_noise(self, num, num_sensors, *, dtype, device=None, generator=None):
        return self._distribution(dtype, device).sample((num, num_sensors), generator=generator)

    def extra_repr(self) -> str:
        return f"kappa={self.kappa}"


class TangentGaussianNoise(SensorNoise):
    """Isotropic Gaussian in the tangent space of SO(3): ``R exp(hat(v))``.

    Args:
        std_deg: per-axis std of the rotation vector (degrees); default ``2/√kappa`` rad.
        kappa: the vMF concentration whose dispersion to match when ``std_deg`` is None.
    """

    def __init__(self, std_deg: float | None = None, kappa: float = 1000.0) -> None:
        super().__init__()
        self.std = (math.radians(_positive("std_deg", std_deg)) if std_deg is not None
                    else float(kappa_to_tangent_std(_positive("kappa", kappa))))

    def sensor_noise(self, num, num_sensors, *, dtype, device=None, generator=None):
        v = torch.randn(num, num_sensors, 3, generator=generator, dtype=dtype, device=device)
        return axis_angle_to_quaternion(v * self.std)

    def extra_repr(self) -> str:
        return f"std_deg={math.degrees(self.std):.3f}"


class PassiveGaussianNoise(SensorNoise):
    """The paper's GN baseline: ``N(0, std²)`` on each passive joint parameter after ``g^{-1}``.

    Args:
        std_deg: std (degrees); default ``2/√kappa`` rad (3.6° at κ = 1000, the "equivalent
            dispersion" of the vMF model).
        kappa: see ``std_deg``.
    """

    def __init__(self, std_deg: float | None = None, kappa: float = 1000.0) -> None:
        super().__init__()
        self.std = (math.radians(_positive("std_deg", std_deg)) if std_deg is not None
                    else float(kappa_to_tangent_std(_positive("kappa", kappa))))

    def perturb_passive(self, theta, passive_index, generator=None):
        return add_parameter_noise(theta, passive_index.flatten(), self.std, generator)

    def extra_repr(self) -> str:
        return f"std_deg={math.degrees(self.std):.3f}"
