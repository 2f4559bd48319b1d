"""The gauge of a rig refined from the subject alone, and how it is held.

Moving the world by a similarity ``x -> s Q x + d`` and every camera with it (``R -> R Qᵀ``,
``c -> s Q c + d``; the 3D points likewise) changes no pixel: with the 3D points free, a
refinement of rotations and centres cannot tell these 7 directions (3 rotation, 3 translation,
1 scale) from a better calibration, and a solver left alone drifts along them. With the 3D
points free, shifting every camera's time offset by the same amount is a gauge too (the
trajectory shifts with them).

In the values of :mod:`torchmocap.cameras.rig_parameters` (rotation ω in world axes, centre
update δc) the similarity's tangent is ``ω_c = −φ`` for every camera, ``δc_c = φ × c_c + d +
σ c_c``. :func:`gauge_constraints` removes it by linear constraints on the refined parameters:

* ``"mean"`` (default): ``Σ_c ω_c = 0`` (the cameras' mean orientation is kept: the world's
  axes, its up axis in particular, stay those of the given calibration on average),
  ``Σ_c δc_c = 0`` (their mean centre is kept: the world's origin), and ``Σ_c (c_c − c̄)·δc_c
  = 0`` (their RMS distance from that centre is kept, to first order: the world's scale and
  units).
* a camera index ``r``: ``ω_r = 0``, ``δc_r = 0`` (that camera does not move) and
  ``Σ_c (c_c − c_r)·δc_c = 0`` (the other cameras' RMS distance from it is kept, to first
  order).
* ``"none"``: no constraint (priors alone hold the gauge, weakly).

The rotation constraints are set only when rotations *and* centres are refined (rotating every
camera about its own centre is not a gauge), the translation and scale ones when centres are.
Time offsets: ``"mean"`` (``Σ_c δ_c = 0``), a camera index (``δ_r = 0``) or ``"none"``.

The solver works in the null space of the constraints (``z = D N y``,
:class:`~torchmocap.cameras.rig_parameters.RigParametrization`), so no step leaves it: the
constraints hold to rounding at every iteration, and the distance one to first order: the mean
squared distance grows by exactly the mean squared centre update, ``Σ_c |δc_c|² / C`` (a
relative scale change of ``|δc|² / 2r²``: 4·10⁻⁶ for 1 cm updates of cameras 3.5 m apart,
10⁻⁴ for 5 cm).

Example:
    >>> from torchmocap.cameras import make_ring_rig
    >>> from torchmocap.cameras.rig_parameters import RigParametrization
    >>> par = RigParametrization(make_ring_rig(3), ("rotation", "translation", "time_offset"))
    >>> par.constraints.shape                  # 7 for the similarity, 1 for the time offsets
    torch.Size([8, 21])
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmocap.cameras.projection import RefinementError

__all__ = ["check_gauge", "gauge_constraints", "similarity_tangents"]


def check_gauge(gauge, num_cameras: int, name: str = "gauge") -> str | int:
    """``"mean"``, ``"none"`` or a camera index in ``[0, C)``; else a
    :class:`~torchmocap.cameras.RefinementError` naming ``name``."""
    if isinstance(gauge, str) and gauge in ("mean", "none"):
        return gauge
    if isinstance(gauge, int) and not isinstance(gauge, bool) and 0 <= gauge < num_cameras:
        return gauge
    raise RefinementError(f"{name}: expected 'mean', 'none' or a reference camera index in "
                          f"[0, {num_cameras}), got {gauge!r}")


def gauge_constraints(par, gauge: str | int = "mean", time_gauge: str | int = "mean") -> Tensor:
    """The linear gauge constraints ``G z = 0`` on a parametrisation's refined parameters.

    Args:
        par: a :class:`~torchmocap.cameras.rig_parameters.RigParametrization` (its
            ``free_camera``, ``free_value``, ``groups`` and the given rig are read).
        gauge: ``"mean"``, a reference camera index, or ``"none"`` (module docstring).
        time_gauge: ``"mean"``, a reference camera index, or ``"none"``.

    Returns:
        ``G (g, n_z)`` float64 (``g = 0`` when nothing is constrained).
    """
    C = par.num_cameras
    gauge = check_gauge(gauge, C, "gauge")
    time_gauge = check_gauge(time_gauge, C, "time_gauge")
    cams, vals = par.free_camera.tolist(), par.free_value.tolist()
    col = {(c, v): j for j, (c, v) in enumerate(zip(cams, vals))}
    n = len(cams)
    centres = -(par.R.transpose(-1, -2) @ par.t.unsqueeze(-1)).squeeze(-1)  # (C, 3)
    rows: list[Tensor] = []

    def row(entries) -> None:
        r = torch.zeros(n, dtype=torch.float64, device=centres.device)
        for (c, v), w in entries:
            if (c, v) in col:
                r[col[(c, v)]] += w
        if bool((r != 0).any()):
            rows.append(r)

    has_centre = "translation" in par.groups
    if gauge != "none" and has_centre:
        everyone = range(C) if gauge == "mean" else [gauge]
        if "rotation" in par.groups:
            for a in range(3):
                row([((c, a), 1.0) for c in everyone])
        for a in range(3):
            row([((c, 3 + a), 1.0) for c in everyone])
        origin = centres.mean(0) if gauge == "mean" else centres[gauge]
        arm = centres - origin
        row([((c, 3 + a), float(arm[c, a])) for c in range(C) for a in range(3)])
    if time_gauge != "none" and "time_offset" in par.groups:
        everyone = range(C) if time_gauge == "mean" else [time_gauge]
        row([((c, 12), 1.0) for c in everyone])
    if not rows:
        return torch.zeros(0, n, dtype=torch.float64, device=centres.device)
    return torch.stack(rows)


def similarity_tangents(par) -> Tensor:
    """The similarity's 7 tangent directions in ``z`` (rotation about the world's x, y, z,
    translation along x, y, z, scale), restricted to the refined parameters: ``(7, n_z)``.

    Directions whose values are not all refined (a rotation of the world when only rotations
    are refined) are not gauges of that parametrisation; they are returned all the same (the
    entries of the refined values), for tests and diagnostics.
    """
    C = par.num_cameras
    centres = -(par.R.transpose(-1, -2) @ par.t.unsqueeze(-1)).squeeze(-1)
    full = torch.zeros(7, C, 13, dtype=torch.float64, device=centres.device)
    eye = torch.eye(3, dtype=torch.float64, device=centres.device)
    for a in range(3):
        full[a, :, 0:3] = -eye[a]
        full[a, :, 3:6] = torch.linalg.cross(eye[a].expand(C, 3), centres)
        full[3 + a, :, 3:6] = eye[a]
    full[6, :, 3:6] = centres
    flat = full.reshape(7, -1)
    return flat[:, par.free_camera * 13 + par.free_value]
