"""A differentiable parametrisation of a :class:`~torchmocap.cameras.CameraRig` around a given
calibration: what a self-calibration refines.

Every camera has the same 13 *values* (:data:`PARAMETER_NAMES`), all zero at the given
calibration:

==========  =========================  =====================================================
index       value                      how it changes the camera
==========  =========================  =====================================================
0–2         ``rotation`` ω (rad)       ``R' = R exp([ω]×)``: a rotation of the camera about
                                       its own centre, ω in **world** axes
3–5         ``centre`` δc (m)          ``c' = c + δc`` (world); the translation follows,
                                       ``t' = −R' c'``
6, 7        ``log_fx``, ``log_fy``     ``fx' = fx e^{log_fx}``, ``fy' = fy e^{log_fy}`` (the
                                       skew scales with ``fx``)
8, 9        ``cx``, ``cy`` (px)        ``cx' = cx + δcx``, ``cy' = cy + δcy``
10, 11      ``k1``, ``k2``             ``k1' = k1 + δk1``, ``k2' = k2 + δk2``
12          ``time_offset`` (frames)   the camera's frame ``t`` shows the subject at time
                                       ``t + δ`` (used by the reprojection, not by the rig)
==========  =========================  =====================================================

A rotation about the camera's centre and a move of the centre, rather than an update of
``t``, keep the two apart: with ``t`` updated, a small rotation of a camera 3 m from the origin
would also move its centre by centimetres.

Which values are refined is chosen by **group** (:data:`RIG_GROUPS`): ``rotation`` (3 per
camera), ``translation`` (the centre, 3), ``focal`` (one log-scale shared by ``fx`` and ``fy``)
or ``focal_xy`` (the two separately), ``principal_point`` (2), ``distortion`` (``k1``, ``k2``)
and ``time_offset`` (1). The refined parameters ``z`` (``n_z`` of them, camera by camera, in
group order) map linearly to the values: ``values = A z`` (``A`` ties ``log_fx = log_fy`` for
``focal``). The gauge (:mod:`torchmocap.cameras.rig_gauge`) restricts ``z`` to a subspace,
``z = D N y``, ``D`` the :data:`PARAMETER_UNITS` (so every coordinate of ``y`` moves pixels by
comparable amounts: the solver's conditioning) and ``N`` an orthonormal basis of the gauge's
null space. A solver works on ``y``; :meth:`RigParametrization.values` gives the values.

Shapes: ``C`` cameras, ``P = 13`` values per camera.

Example:
    >>> from torchmocap.cameras import make_ring_rig
    >>> par = RigParametrization(make_ring_rig(4), groups=("rotation", "translation", "focal"))
    >>> par.num_free, par.num_parameters          # 4 x 7 refined, less the 7-DoF gauge
    (28, 21)
    >>> values = par.values(torch.zeros(par.num_parameters, dtype=torch.float64))
    >>> K, R, t, dist = par.camera_tensors(values)
    >>> K.shape, values.shape
    (torch.Size([4, 3, 3]), torch.Size([4, 13]))
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchmocap.cameras.projection import RefinementError, camera_centers
from torchmocap.cameras.rig import CameraRig
from torchmocap.cameras.rig_gauge import gauge_constraints
from torchmocap.geometry import so3_exp

__all__ = [
    "PARAMETER_NAMES",
    "PARAMETER_UNITS",
    "RIG_GROUPS",
    "RefinementError",
    "RigParametrization",
    "apply_rig_parameters",
    "check_groups",
]

#: the 13 values of every camera, in order
PARAMETER_NAMES = ("rot_x", "rot_y", "rot_z", "centre_x", "centre_y", "centre_z", "log_fx",
                   "log_fy", "cx", "cy", "k1", "k2", "time_offset")
NUM_VALUES = len(PARAMETER_NAMES)

#: the value indices of each group (``focal`` is one parameter setting both ``log_fx`` and
#: ``log_fy``; ``focal_xy`` two)
RIG_GROUPS: dict[str, tuple[tuple[int, ...], ...]] = {
    "rotation": ((0,), (1,), (2,)),
    "translation": ((3,), (4,), (5,)),
    "focal": ((6, 7),),
    "focal_xy": ((6,), (7,)),
    "principal_point": ((8,), (9,)),
    "distortion": ((10,), (11,)),
    "time_offset": ((12,),),
}

#: a unit of each value in which the solver works: about a pixel's worth of change for a
#: camera of ~1000 px focal length a few metres away (rad, m, log-scale, px, 1, frames)
PARAMETER_UNITS = (1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1.0, 1.0, 1e-3, 1e-3, 1e-2)

#: the groups refined when none are named
DEFAULT_GROUPS = ("rotation", "translation", "focal")


def check_groups(groups) -> tuple[str, ...]:
    """``groups`` as a tuple of known group names (each once; ``focal`` and ``focal_xy``
    exclusive), or a :class:`RefinementError` naming the unknown one."""
    if isinstance(groups, str):
        groups = (groups,)
    try:
        groups = tuple(groups)
    except TypeError:
        raise RefinementError(f"groups: expected a sequence of group names from "
                              f"{list(RIG_GROUPS)}, got {groups!r}") from None
    for g in groups:
        if g not in RIG_GROUPS:
            raise RefinementError(f"groups: unknown parameter group {g!r}; expected names from "
                                  f"{list(RIG_GROUPS)}")
    if len(set(groups)) != len(groups):
        raise RefinementError(f"groups: a group is named twice in {list(groups)}")
    if "focal" in groups and "focal_xy" in groups:
        raise RefinementError("groups: 'focal' (one scale for fx and fy) and 'focal_xy' (two) "
                              "exclude each other; name one")
    if not groups:
        raise RefinementError(f"groups: expected at least one group from {list(RIG_GROUPS)}")
    return tuple(g for g in RIG_GROUPS if g in groups)  # canonical order


def apply_rig_parameters(values: Tensor, K: Tensor, R: Tensor, t: Tensor, dist: Tensor
                         ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The cameras ``values`` make of a given calibration (differentiable in ``values``).

    Args:
        values: ``(C, 13)`` (:data:`PARAMETER_NAMES`); zeros give the calibration back.
        K: ``(C, 3, 3)`` intrinsics, R ``(C, 3, 3)`` world-to-camera rotations, t ``(C, 3)``
            translations (metres), dist ``(C, 5)`` (k1, k2, p1, p2, k3): the given cameras.

    Returns:
        ``K', R', t', dist'`` of the same shapes (``values``' dtype). The time offset (value
        12) does not change a camera.

    Example:
        >>> from torchmocap.cameras import make_ring_rig
        >>> rig = make_ring_rig(2)
        >>> v = torch.zeros(2, 13, dtype=torch.float64)
        >>> v[:, 6:8] = torch.tensor(1.1, dtype=torch.float64).log()   # focal +10 %
        >>> K, R, t, d = apply_rig_parameters(v, rig.K, rig.R, rig.t, rig.dist)
        >>> tuple(round(x, 9) for x in (K[:, 0, 0] / rig.K[:, 0, 0]).tolist())
        (1.1, 1.1)
    """
    C = K.shape[0]
    if values.shape != (C, NUM_VALUES):
        raise RefinementError(f"values: expected shape ({C}, {NUM_VALUES}), got "
                              f"{tuple(values.shape)}")
    dt = values.dtype
    K, R, t, dist = (x.to(device=values.device, dtype=dt) for x in (K, R, t, dist))
    R_new = R @ so3_exp(values[:, 0:3])
    c_new = camera_centers(R, t) + values[:, 3:6]
    t_new = -(R_new @ c_new.unsqueeze(-1)).squeeze(-1)
    sx, sy = values[:, 6].exp(), values[:, 7].exp()
    zero, one = torch.zeros_like(sx), torch.ones_like(sx)
    row0 = torch.stack([K[:, 0, 0] * sx, K[:, 0, 1] * sx, K[:, 0, 2] + values[:, 8]], -1)
    row1 = torch.stack([zero, K[:, 1, 1] * sy, K[:, 1, 2] + values[:, 9]], -1)
    row2 = torch.stack([zero, zero, one], -1)
    K_new = torch.stack([row0, row1, row2], -2)
    dist_new = torch.cat([dist[:, 0:2] + values[:, 10:12], dist[:, 2:]], -1)
    return K_new, R_new, t_new, dist_new


def _unit_basis(G: Tensor, n: int, like: Tensor) -> Tensor:
    """An orthonormal basis ``(n, n - rank)`` of the null space of ``G (g, n)``."""
    if G.shape[0] == 0:
        return torch.eye(n, dtype=like.dtype, device=like.device)
    _, s, Vh = torch.linalg.svd(G, full_matrices=True)
    rank = int((s > 1e-10 * s.max()).sum())
    return Vh[rank:].T.contiguous()


class RigParametrization:
    """The refined parameters of a rig: groups, the map to the 13 values per camera, the gauge.

    Args:
        rig: the given calibration (its values are the zero point; kept as float64 copies).
        groups: refined groups, names from :data:`RIG_GROUPS` (default
            ``("rotation", "translation", "focal")``).
        gauge: how the 7 similarity degrees of freedom of the world are held
            (:func:`~torchmocap.cameras.rig_gauge.gauge_constraints`): ``"mean"`` (default),
            a reference camera's index, or ``"none"``.
        time_gauge: the same for the time offsets: ``"mean"``, a camera index or ``"none"``.

    Attributes:
        groups: the refined groups (canonical order).
        selection: ``A (C·13, n_z)``: values (flattened) = ``A z``.
        free_names: the ``n_z`` names ``"<camera>.<value>"`` of ``z`` (``log_f`` for a shared
            focal scale).
        free_camera: ``(n_z,)`` the camera of each refined parameter.
        free_value: ``(n_z,)`` the (first) value index of each refined parameter.
        constraints: ``G (g, n_z)``, the linear gauge constraints ``G z = 0``.
        basis: ``(n_z, n_y)`` ``D N``: ``z = basis @ y``.

    Raises:
        RefinementError: an unknown group or gauge setting (named).
    """

    def __init__(self, rig: CameraRig, groups: Sequence[str] = DEFAULT_GROUPS,
                 gauge: str | int = "mean", time_gauge: str | int = "mean") -> None:
        if not isinstance(rig, CameraRig):
            raise RefinementError(f"rig: expected a CameraRig, got {type(rig).__name__}")
        self.groups = check_groups(groups)
        self.rig = rig
        dev = rig.K.device
        f64 = dict(dtype=torch.float64, device=dev)
        self.K, self.R = rig.K.to(**f64), rig.R.to(**f64)
        self.t, self.dist = rig.t.to(**f64), rig.dist.to(**f64)
        self.image_size = rig.image_size
        self.names = list(rig.names)
        C = rig.num_cameras
        cols, cams, firsts, names = [], [], [], []
        for c in range(C):
            for g in self.groups:
                for rows in RIG_GROUPS[g]:
                    col = torch.zeros(C * NUM_VALUES, **f64)
                    for r in rows:
                        col[c * NUM_VALUES + r] = 1.0
                    cols.append(col)
                    cams.append(c)
                    firsts.append(rows[0])
                    names.append(f"{self.names[c]}." + ("log_f" if len(rows) > 1
                                                          else PARAMETER_NAMES[rows[0]]))
        self.selection = torch.stack(cols, 1)
        self.free_camera = torch.tensor(cams, dtype=torch.long, device=dev)
        self.free_value = torch.tensor(firsts, dtype=torch.long, device=dev)
        self.free_names = names
        units = torch.tensor(PARAMETER_UNITS, **f64)[self.free_value]
        self.units = units
        self.gauge, self.time_gauge = gauge, time_gauge
        self.constraints = gauge_constraints(self, gauge, time_gauge)
        self.basis = units[:, None] * _unit_basis(self.constraints * units, len(names), units)

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]

    @property
    def num_free(self) -> int:
        """``n_z``: refined parameters before the gauge."""
        return self.selection.shape[1]

    @property
    def num_parameters(self) -> int:
        """``n_y``: the solver's parameters (refined ones less the gauge's)."""
        return self.basis.shape[1]

    @property
    def refines_time(self) -> bool:
        return "time_offset" in self.groups

    def value_map(self, dtype: torch.dtype | None = None) -> Tensor:
        """``M (C, 13, n_y)``: the values of camera ``c`` are ``M[c] @ y``."""
        M = (self.selection @ self.basis).reshape(self.num_cameras, NUM_VALUES, -1)
        return M if dtype is None else M.to(dtype)

    def values(self, y: Tensor) -> Tensor:
        """The ``(C, 13)`` values of the solver's parameters ``y (n_y,)`` (``y``'s dtype)."""
        if y.shape != (self.num_parameters,):
            raise RefinementError(f"y: expected shape ({self.num_parameters},), got "
                                  f"{tuple(y.shape)}")
        return (self.selection.to(y) @ (self.basis.to(y) @ y)).reshape(self.num_cameras,
                                                                       NUM_VALUES)

    def free_values(self, values: Tensor) -> Tensor:
        """``z (n_z,)``: the refined parameters read off ``values (C, 13)``."""
        return values.reshape(-1)[self.free_camera * NUM_VALUES + self.free_value]

    def camera_tensors(self, values: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``K, R, t, dist`` of ``values (C, 13)`` (:func:`apply_rig_parameters`)."""
        return apply_rig_parameters(values, self.K, self.R, self.t, self.dist)

    def refined_rig(self, values: Tensor, dtype: torch.dtype | None = None) -> CameraRig:
        """The :class:`CameraRig` of ``values (C, 13)`` (detached; ``dtype`` default: the given
        rig's), with the given rig's image sizes and names."""
        K, R, t, dist = (x.detach().to(torch.float64) for x in self.camera_tensors(values))
        # re-orthonormalise R (exp of a float64 rotation vector is orthonormal to ~1e-16)
        U, _, Vh = torch.linalg.svd(R)
        R = U @ Vh
        rig = CameraRig(K, R, t, self.image_size, dist, self.names)
        return rig.to(dtype or self.rig.K.dtype)

    def time_offsets(self, values: Tensor) -> Tensor:
        """``(C,)`` time offsets in frames (value 12)."""
        return values[:, 12]

    def __repr__(self) -> str:
        return (f"RigParametrization(cameras={self.num_cameras}, groups={list(self.groups)}, "
                f"gauge={self.gauge!r}, time_gauge={self.time_gauge!r}, "
                f"parameters={self.num_parameters})")
