"""Isotropic Gaussian on SO(3) in the tangent space, and the Gaussian-on-parameters baseline.

``TangentGaussianSO3(loc, scale)``: ``R = loc @ exp(hat(scale * eps))``, ``eps ~ N(0, I_3)``.
At ``scale = 2/sqrt(kappa)`` it is statistically indistinguishable from vMF quaternion noise with
concentration ``kappa >= 100`` (REFERENCE §2). ``log_prob`` is the density of the *tangent
vector* ``log(loc^T R)`` under ``N(0, scale^2 I_3)`` (not a density w.r.t. the Haar measure; the
two differ by the Jacobian of the exp map, ``~1`` for small angles, and the tangent density
ignores the wrap-around at ``pi``).

:func:`add_parameter_noise` / :class:`ParameterGaussianNoise` are Pons-Moll et al.'s "Gaussian"
noise model (GN, §4.2): Gaussian noise added to the *passive joint parameters* (Euler-type
angles) after inverse kinematics. Its spread in rotation space depends on the pose (anisotropic
near gimbal-like configurations), which is what the paper's Fig. 5 shows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch.distributions import Distribution, constraints

from torchmocap.geometry import (
    axis_angle_to_quaternion,
    matrix_to_quaternion,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_axis_angle,
    quaternion_to_matrix,
)

__all__ = ["TangentGaussianSO3", "ParameterGaussianNoise", "add_parameter_noise"]


class TangentGaussianSO3(Distribution):
    """Isotropic tangent-space Gaussian around ``loc`` on SO(3).

    Args:
        loc: ``(*batch, 4)`` unit quaternions (w, x, y, z) or ``(*batch, 3, 3)`` rotation
            matrices; samples use the same representation.
        scale: ``(*batch)`` (broadcastable) per-axis standard deviation in radians, > 0.
        validate_args: check ``loc`` (unit norm / finite) and ``scale`` (default: checked).

    Example:
        >>> d = TangentGaussianSO3(torch.tensor([1.0, 0, 0, 0]), torch.tensor(0.06))
        >>> d.sample((5,)).shape
        torch.Size([5, 4])
    """

    arg_constraints = {"scale": constraints.positive}
    has_rsample = True

    def __init__(
        self, loc: torch.Tensor, scale: torch.Tensor | float, validate_args: bool | None = None
    ) -> None:
        if not isinstance(loc, torch.Tensor):
            raise TypeError(f"loc: expected a torch.Tensor, got {type(loc).__name__}")
        if loc.shape[-1:] == (4,):
            self.representation = "quaternion"
            q = loc
        elif loc.shape[-2:] == (3, 3):
            self.representation = "matrix"
            q = None
        else:
            raise ValueError(f"loc: expected (*, 4) quaternions or (*, 3, 3) rotations, "
                             f"got {tuple(loc.shape)}")
        scale = torch.as_tensor(scale, dtype=loc.dtype, device=loc.device)
        if validate_args is not False:
            if not bool(torch.isfinite(loc).all()):
                raise ValueError("loc: expected finite values, found NaN or inf")
            tol = 1e-6 if loc.dtype == torch.float64 else 1e-4
            if q is not None and float((q.norm(dim=-1) - 1).abs().max()) > tol:
                raise ValueError(f"loc: expected unit quaternions (tolerance {tol})")
            if q is None:
                eye = torch.eye(3, dtype=loc.dtype, device=loc.device)
                if float((loc.transpose(-1, -2) @ loc - eye).abs().max()) > 10 * tol:
                    raise ValueError("loc: expected rotation matrices (R^T R = I)")
            if not bool(torch.isfinite(scale).all()) or bool((scale <= 0).any()):
                raise ValueError("scale: expected finite values > 0")
        ev = loc.shape[-1:] if q is not None else loc.shape[-2:]
        lb = loc.shape[: loc.dim() - len(ev)]
        batch_shape = torch.broadcast_shapes(lb, scale.shape)
        self.loc = loc.expand(*batch_shape, *ev)
        self.scale = scale.expand(batch_shape)
        super().__init__(batch_shape, torch.Size(ev), validate_args=False)

    def _loc_quaternion(self) -> torch.Tensor:
        if self.representation == "quaternion":
            return self.loc
        return matrix_to_quaternion(self.loc)

    def sample_tangent(
        self, sample_shape: torch.Size | tuple[int, ...] = (),
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Tangent vectors ``sample_shape + batch_shape + (3,)`` (radians)."""
        shape = torch.Size(sample_shape) + self.batch_shape
        eps = torch.randn(*shape, 3, generator=generator, dtype=self.loc.dtype,
                          device=self.loc.device)
        return eps * self.scale[..., None]

    def rsample(
        self, sample_shape: torch.Size | tuple[int, ...] = (),
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Reparameterised draw ``loc * exp(v)``, ``v ~ N(0, scale^2 I)``; same representation."""
        v = self.sample_tangent(sample_shape, generator)
        if self.representation == "quaternion":
            return quaternion_multiply(self.loc, axis_angle_to_quaternion(v))
        from torchmocap.geometry import so3_exp

        return self.loc @ so3_exp(v)

    def sample(
        self, sample_shape: torch.Size | tuple[int, ...] = (),
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """``sample_shape + batch_shape + event_shape`` rotations (no gradient)."""
        with torch.no_grad():
            return self.rsample(sample_shape, generator)

    def tangent(self, value: torch.Tensor) -> torch.Tensor:
        """``log(loc^-1 value)`` ``(*, 3)`` for quaternion ``(*, 4)`` or matrix ``(*, 3, 3)``."""
        q = value if self.representation == "quaternion" else matrix_to_quaternion(value)
        return quaternion_to_axis_angle(quaternion_multiply(
            quaternion_conjugate(self._loc_quaternion()), q))

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        """Log density of the tangent vector ``log(loc^-1 value)`` under ``N(0, scale^2 I_3)``."""
        v = self.tangent(value)
        s = self.scale
        return -0.5 * (v * v).sum(-1) / (s * s) - 3 * torch.log(s) - 1.5 * math.log(2 * math.pi)

    def entropy(self) -> torch.Tensor:
        """Entropy of the tangent Gaussian, ``3/2 log(2 pi e) + 3 log scale``."""
        return 1.5 * math.log(2 * math.pi * math.e) + 3 * torch.log(self.scale)

    def to_quaternion(self, value: torch.Tensor) -> torch.Tensor:
        """Convert samples to quaternions (identity for the quaternion representation)."""
        return value if self.representation == "quaternion" else matrix_to_quaternion(value)

    def to_matrix(self, value: torch.Tensor) -> torch.Tensor:
        """Convert samples to rotation matrices."""
        return quaternion_to_matrix(value) if self.representation == "quaternion" else value


def add_parameter_noise(
    theta: torch.Tensor,
    indices: Sequence[int] | torch.Tensor,
    std: float | torch.Tensor,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Add ``N(0, std^2)`` noise to ``theta[..., indices]`` (Pons-Moll's GN baseline).

    Args:
        theta: ``(*, D)`` poses.
        indices: ``(K,)`` DoF indices that receive noise (the passive parameters).
        std: scalar or ``(K,)`` standard deviation in radians.
        generator: optional ``torch.Generator``.
    Returns:
        ``(*, D)`` new tensor.
    """
    idx = torch.as_tensor(indices, dtype=torch.long, device=theta.device)
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= theta.shape[-1]):
        raise ValueError(f"indices: expected DoF indices in [0, {theta.shape[-1]}), "
                         f"got {idx.tolist()}")
    std = torch.as_tensor(std, dtype=theta.dtype, device=theta.device)
    if bool((std < 0).any()) or not bool(torch.isfinite(std).all()):
        raise ValueError("std: expected finite values >= 0")
    noise = torch.randn(*theta.shape[:-1], idx.numel(), generator=generator,
                        dtype=theta.dtype, device=theta.device) * std
    out = theta.clone()
    out[..., idx] = out[..., idx] + noise
    return out


class ParameterGaussianNoise(torch.nn.Module):
    """Module form of :func:`add_parameter_noise` with fixed indices and std.

    ``log_prob(delta)`` gives the log density of a perturbation ``delta`` ``(*, K)``.
    """

    def __init__(self, indices: Sequence[int], std: float | Sequence[float]) -> None:
        super().__init__()
        self.register_buffer("indices", torch.as_tensor(list(indices), dtype=torch.long))
        std_t = torch.as_tensor(std, dtype=torch.float32)
        if bool((std_t < 0).any()):
            raise ValueError("std: expected values >= 0")
        self.register_buffer("std", std_t)

    def forward(self, theta: torch.Tensor, generator: torch.Generator | None = None):
        return add_parameter_noise(theta, self.indices, self.std.to(theta.dtype), generator)

    def log_prob(self, delta: torch.Tensor) -> torch.Tensor:
        s = self.std.to(delta.dtype).expand(delta.shape[-1:])
        z = delta / s
        return (-0.5 * z * z - torch.log(s) - 0.5 * math.log(2 * math.pi)).sum(-1)
