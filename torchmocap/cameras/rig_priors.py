"""Gaussian priors keeping a refined rig near its given calibration.

Each refined parameter ``z_j`` gets the residual ``z_j / width_j`` (zero mean: the given
calibration), added to the whitened reprojection residuals. The widths are stated per group in
the units a person reads (:class:`RigPriors`); ``None`` leaves a group without a prior.

What the data barely see needs them: focal length against the camera's distance (a subject
small in the image is nearly a parallel projection: a longer focal length from further away
gives almost the same pixels), the principal point against small rotations (both shift the
image), radial distortion against focal length near the image centre, and the time offsets
when the subject hardly moves. The defaults are wide enough to let a typical calibration error
(a few degrees, centimetres, per cent) through, narrow enough to hold what the subject cannot
decide; the refinement reports which parameters its data did not determine
(:mod:`torchmocap.cameras.bundle_adjustment`).

Example:
    >>> from torchmocap.cameras import make_ring_rig
    >>> from torchmocap.cameras.rig_parameters import RigParametrization
    >>> par = RigParametrization(make_ring_rig(2), ("rotation", "focal"), gauge="none")
    >>> tuple(round(w, 6) for w in RigPriors(rotation_deg=2.0).widths(par)[[0, 3]].tolist())
    (0.034907, 0.04879)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from torchmocap.cameras.projection import RefinementError

__all__ = ["RigPriors"]

_FIELDS = {  # field -> (value indices, description)
    "rotation_deg": ((0, 1, 2), "degrees per axis"),
    "translation_m": ((3, 4, 5), "metres per axis of the camera centre"),
    "focal_percent": ((6, 7), "per cent of the focal length"),
    "principal_point_px": ((8, 9), "pixels per coordinate"),
    "distortion": ((10, 11), "absolute change of k1 and k2"),
    "time_offset_frames": ((12,), "frames"),
}


@dataclass(frozen=True)
class RigPriors:
    """Prior widths (one standard deviation) of the refined parameters; ``None`` = no prior.

    Attributes:
        rotation_deg: rotation of a camera about each world axis, degrees (default 5).
        translation_m: camera centre along each world axis, metres (default 0.25).
        focal_percent: focal length (each of fx, fy), per cent (default 5: the parameter is
            the log-scale, width ``log(1 + 5/100)``).
        principal_point_px: each principal point coordinate, pixels of the rig's images
            (default 20).
        distortion: k1 and k2, absolute (default 0.05).
        time_offset_frames: time offset, frames (default 2).
    """

    rotation_deg: float | None = 5.0
    translation_m: float | None = 0.25
    focal_percent: float | None = 5.0
    principal_point_px: float | None = 20.0
    distortion: float | None = 0.05
    time_offset_frames: float | None = 2.0

    def __post_init__(self) -> None:
        for name, (_, what) in _FIELDS.items():
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v <= 0:
                raise RefinementError(f"priors.{name}: expected a width in {what} > 0 (or None "
                                      f"for no prior), got {v!r}")

    @classmethod
    def from_dict(cls, data) -> RigPriors:
        """From a mapping of some of the fields (unknown keys are named in the error)."""
        if isinstance(data, RigPriors):
            return data
        if data is None:
            return cls()
        if not hasattr(data, "keys"):
            raise RefinementError(f"priors: expected a RigPriors or a mapping of "
                                  f"{list(_FIELDS)}, got {data!r}")
        unknown = sorted(set(data) - set(_FIELDS))
        if unknown:
            raise RefinementError(f"priors: unknown setting(s) {unknown}; expected "
                                  f"{list(_FIELDS)}")
        return cls(**dict(data))

    def to_dict(self) -> dict:
        return asdict(self)

    def value_widths(self) -> list[float]:
        """Width of each of the 13 values in its own unit (inf without a prior)."""
        out = [math.inf] * 13
        for name, (idx, _) in _FIELDS.items():
            v = getattr(self, name)
            if v is None:
                continue
            w = {"rotation_deg": math.radians(v), "focal_percent": math.log1p(v / 100)}.get(
                name, float(v))
            for i in idx:
                out[i] = w
        return out

    def widths(self, par) -> Tensor:
        """``(n_z,)`` widths of a parametrisation's refined parameters (inf: no prior)."""
        w = torch.tensor(self.value_widths(), dtype=torch.float64, device=par.free_value.device)
        return w[par.free_value]

    def check_time(self, num_frames: int) -> None:
        """A time-offset prior wider than the sequence is refused (naming the setting)."""
        v = self.time_offset_frames
        if v is not None and v >= num_frames - 1:
            raise RefinementError(f"priors.time_offset_frames: a width of {v:g} frames is not "
                                  f"smaller than the {num_frames} refined frames")
