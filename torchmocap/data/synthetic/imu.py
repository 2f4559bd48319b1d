"""Synthetic inertial sensors: orientations of body-worn IMUs with the error sources of
Pons-Moll et al. (2010, §4.2).

For sensor ``s`` on bone ``b`` at frame ``t`` (``R_TB`` the ground-truth bone frame)::

    clean:    R_TS(t) = R_TB(t) · R_BS                          (exact, stored for reference)
    measured: R_TS(t) = Rz(ω_s t) · R_mis · R_TB(t + δ) · R_BS · N_s(t)

* ``R_BS`` — fixed sensor-to-bone offset (uniform random, seeded; or identity);
* ``N_s(t)`` — device noise in the sensor frame: vMF on S³ around the identity quaternion
  (concentration κ; the paper's ``q̃ = q ∘ q_w``, eq. 16) or an isotropic tangent Gaussian;
* ``R_mis`` — misalignment of the inertial and tracking frames (fixed angle, random axis),
  shared by all sensors, applied on the left;
* ``δ`` — desynchronisation in frames: ``R_TB`` is slerped between neighbouring frames
  (clamped at the ends of the clip);
* ``Rz(ω_s t)`` — heading drift about world z at ``ω_s = ± drift_deg_per_min`` (seeded sign);
* dropped samples — Bernoulli per sample (never the first frame); the last valid measurement is
  held and ``valid`` is False (no NaN).

Quaternions are w, x, y, z with ``w >= 0``. Shapes: ``T`` frames, ``S`` sensors, ``J`` joints.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmocap.data.imu import ImuData, SensorPlacementError, resolve_sensors
from torchmocap.geometry import (
    axis_angle_to_quaternion,
    matrix_to_quaternion,
    quaternion_canonical,
    quaternion_multiply,
    quaternion_slerp,
    random_quaternion,
)

__all__ = ["synthesize_imu"]


def _axis_angle(angle: Tensor, generator: torch.Generator, dtype: torch.dtype) -> Tensor:
    """Quaternions ``(*, 4)`` of rotations by ``angle (*)`` about uniform random axes."""
    axis = torch.randn(*angle.shape, 3, generator=generator, dtype=torch.float64)
    axis = torch.nn.functional.normalize(axis, dim=-1).to(dtype)
    return axis_angle_to_quaternion(axis * angle[..., None])


def _z_rotation(angle: Tensor) -> Tensor:
    h = angle / 2
    z = torch.zeros_like(h)
    return torch.stack([torch.cos(h), z, z, torch.sin(h)], -1)


def _device_noise(shape: tuple[int, ...], noise: str, kappa: float, tangent_std_deg: float,
                  generator: torch.Generator, dtype: torch.dtype, dof: float = 3.0) -> Tensor:
    if noise == "none":
        q = torch.zeros(*shape, 4, dtype=dtype)
        q[..., 0] = 1
        return q
    if noise == "vmf":
        from torchmocap.distributions import VonMisesFisher

        mu = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
        q = VonMisesFisher(mu, torch.tensor(float(kappa), dtype=torch.float64)).sample(
            shape, generator=generator)
        return q.to(dtype)
    if noise == "tangent":
        w = torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
        return axis_angle_to_quaternion(w * math.radians(tangent_std_deg)).to(dtype)
    if noise == "student_t":  # multivariate t in the tangent space: Gaussian / sqrt(chi2 / dof)
        w = torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
        g = _chi2_sample(dof, shape, generator)
        w = w * torch.sqrt(dof / g)[..., None]
        # a rotation by more than pi wraps: cap the angle (a t draw that far is a gross outlier)
        ang = w.norm(dim=-1, keepdim=True) * math.radians(tangent_std_deg)
        axis = torch.nn.functional.normalize(w, dim=-1)
        return axis_angle_to_quaternion(axis * ang.clamp(max=math.pi)).to(dtype)
    raise ValueError(f"noise: expected 'vmf', 'tangent', 'student_t' or 'none', got {noise!r}")


def _chi2_sample(dof: float, shape: tuple[int, ...], generator: torch.Generator) -> Tensor:
    """Chi-square draws with ``dof`` degrees of freedom through ``generator`` (torch's gamma
    sampler takes none): the inverse CDF of uniform draws (scipy's ``gammaincinv``; synthesis
    only, not a hot path)."""
    from scipy.special import gammaincinv

    u = torch.rand(*shape, generator=generator, dtype=torch.float64).clamp(1e-12, 1 - 1e-12)
    return 2.0 * torch.from_numpy(gammaincinv(dof / 2.0, u.numpy()))


def synthesize_imu(
    bone_rotations: Tensor,
    joint_names: list[str],
    sensors: dict[str, str],
    tracking: list[str] | tuple[str, ...],
    fps: float,
    generator: torch.Generator,
    offset: str = "random",
    noise: str = "vmf",
    kappa: float = 1000.0,
    tangent_std_deg: float = 3.6,
    misalignment_deg: float | list[float] = 0.0,
    desync_frames: float = 0.0,
    drift_deg_per_min: float = 0.0,
    drop_prob: float = 0.0,
    dof: float = 3.0,
    heading_walk_deg: float = 0.0,
) -> ImuData:
    """Simulate IMU orientation measurements from ground-truth bone frames.

    Args:
        bone_rotations: ``(T, J, 3, 3)`` ground-truth global bone frames ``R_TB``.
        joint_names: ``J`` names (bones are named by the joint at their start).
        sensors: sensor name → bone name.
        tracking: names of the tracking sensors.
        fps: frame rate (for drift in degrees per minute).
        generator: all randomness (offsets, noise, misalignment axis, drops).
        offset, noise, kappa, tangent_std_deg, misalignment_deg, desync_frames,
        drift_deg_per_min, drop_prob, dof, heading_walk_deg: see
        :class:`~torchmocap.data.synthetic.scenario.ImuConfig`.

    Returns:
        :class:`ImuData` (float64 quaternions if ``bone_rotations`` is float64, else float32).

    Raises:
        SensorPlacementError: a sensor's bone is not in ``joint_names``.
        ValueError: malformed shapes or an empty sequence (naming the argument).
    """
    if bone_rotations.dim() != 4 or bone_rotations.shape[-2:] != (3, 3):
        raise ValueError(f"bone_rotations: expected shape (T, J, 3, 3), got "
                         f"{tuple(bone_rotations.shape)}")
    T, J = bone_rotations.shape[:2]
    if T < 1:
        raise ValueError("bone_rotations: expected at least one frame, got 0")
    if J != len(joint_names):
        raise ValueError(f"joint_names: expected {J} names, got {len(joint_names)}")
    unknown = [t for t in tracking if t not in sensors]
    if unknown:
        raise SensorPlacementError(f"tracking: sensors {unknown} are not in sensors "
                                   f"{list(sensors)}")
    idx = resolve_sensors(sensors, joint_names)
    S = len(idx)
    dtype = bone_rotations.dtype
    names = list(sensors)
    q_tb = quaternion_canonical(matrix_to_quaternion(bone_rotations[:, idx]))  # (T, S, 4)

    # fixed offsets R_BS (drawn first so they do not depend on the error settings)
    if offset == "random":
        q_bs = random_quaternion(S, generator=generator, dtype=torch.float64).to(dtype)
    elif offset == "identity":
        q_bs = torch.zeros(S, 4, dtype=dtype)
        q_bs[:, 0] = 1
    else:
        raise ValueError(f"offset: expected 'random' or 'identity', got {offset!r}")
    clean = quaternion_canonical(quaternion_multiply(q_tb, q_bs[None]))

    # misalignment of the inertial frame (always drawn: stable streams across settings)
    if isinstance(misalignment_deg, (list, tuple)):
        lo, hi = float(misalignment_deg[0]), float(misalignment_deg[1])
    else:
        lo = hi = float(misalignment_deg)
    u = torch.rand((), generator=generator, dtype=torch.float64)
    mis_angle = torch.deg2rad(lo + (hi - lo) * u)
    q_mis = _axis_angle(mis_angle, generator, torch.float64).to(dtype)
    signs = torch.where(torch.rand(S, generator=generator, dtype=torch.float64) < 0.5, -1.0, 1.0)
    drift = (signs * math.radians(drift_deg_per_min) / 60.0).to(dtype)  # rad/s
    drops = torch.rand(T, S, generator=generator, dtype=torch.float64) < drop_prob
    drops[0] = False
    n = _device_noise((T, S), noise, kappa, tangent_std_deg, generator, dtype, dof)
    # magnetic disturbance of the heading: a per-sensor random walk about world z
    walk = torch.zeros(T, S, dtype=torch.float64)
    if heading_walk_deg > 0 and T > 1:
        steps = torch.randn(T - 1, S, generator=generator, dtype=torch.float64)
        walk[1:] = torch.cumsum(steps, 0) * math.radians(heading_walk_deg) / math.sqrt(fps)

    # desynchronised bone frames: slerp at t + δ (clamped to the clip)
    if desync_frames != 0.0 and T > 1:
        tt = (torch.arange(T, dtype=torch.float64) + desync_frames).clamp(0, T - 1)
        i0 = tt.floor().long().clamp(max=T - 2)
        w = (tt - i0.to(torch.float64)).to(dtype)
        q_d = quaternion_slerp(q_tb[i0], q_tb[i0 + 1], w[:, None, None])
    else:
        q_d = q_tb
    q = quaternion_multiply(quaternion_multiply(q_d, q_bs[None]), n)
    q = quaternion_multiply(q_mis.expand(T, S, 4), q)
    time_s = torch.arange(T, dtype=dtype) / fps
    q = quaternion_multiply(_z_rotation(drift[None] * time_s[:, None] + walk.to(dtype)), q)
    q = quaternion_canonical(torch.nn.functional.normalize(q, dim=-1))

    # dropped samples: hold the last valid value
    valid = ~drops
    if bool(drops.any()):
        t_idx = torch.arange(T)[:, None].expand(T, S)
        last = torch.where(valid, t_idx, torch.zeros_like(t_idx)).cummax(0).values
        q = torch.gather(q, 0, last[..., None].expand(T, S, 4))
    return ImuData(names, [sensors[n_] for n_ in names],
                   torch.tensor([n_ in tracking for n_ in names]), q, valid, clean, q_bs,
                   q_mis, drift, float(desync_frames))
