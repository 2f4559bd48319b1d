"""``MaskSettings``: every knob of the foreground-mask computation, with a flat dict form.

The dict form (:meth:`MaskSettings.from_dict` / :meth:`MaskSettings.to_dict`) is what a Hydra
config holds (``data.masks.*``); unknown keys and wrong types are errors naming the key, never
coerced. Sizes that depend on the image (morphology, dilation) are fractions of the working
image's height, so a change of ``scale`` keeps their meaning.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

__all__ = ["MaskError", "MaskSettings"]


class MaskError(ValueError):
    """Bad input to the mask computation (names the argument or setting and what was expected)."""


@dataclass(frozen=True)
class MaskSettings:
    """Settings of :func:`~torchmocap.data.recordings.masks.compute_masks` (each documented
    below)."""

    scale: float = 0.25
    """working resolution as a fraction of the input images (0.25: 1920 → 480 px)."""
    median_frames: int = 25
    """frames (evenly spaced) whose per-pixel median is the video's own background estimate."""
    register_plates: bool = True
    """align each background plate to the video's median with an affine warp and a brightness
    gain/offset (robust Gauss–Newton, coarse to fine) before use.
    """
    max_plate_motion: float = 0.02
    """largest corner displacement that registration may find, as a fraction of the image
    diagonal; beyond it the plate is used unwarped (and the report says so).
    """
    plate_agreement: float = 4.0
    """the plate and the median agree where their colour difference is below this many noise
    standard deviations; there the median is used, the plate elsewhere.
    """
    plate_dilation: float = 0.004
    """the region where the plate replaces the median is grown by this fraction of the image
    height (the subject's blurred outline).
    """
    plate_near_subject: bool = True
    """with keypoints, the plate replaces the median only near the subject (within
    ``subject_radius`` of its keypoints' neighbourhood graph in any of the median's frames):
    elsewhere a disagreement is the plate's own clutter — people, moved objects — and the
    video's median is the background there. Without keypoints (or when a view has none) the
    plate is used wherever the two disagree.
    """
    subject_radius: float = 0.1
    """that distance as a fraction of the subject's extent in the view."""
    threshold: float = 4.0
    """a pixel is foreground when its chromatic distortion (or a brightness change outside the
    shadow/highlight range) exceeds this many noise standard deviations.
    """
    min_noise: float = 1.5
    """floor of the per-camera noise standard deviation (grey levels, 0–255)."""
    shadow_min: float = 0.5
    """darkest brightness ratio (frame/background along the background colour) still taken for a
    shadow when the chromaticity is unchanged.
    """
    highlight_max: float = 1.25
    """brightest such ratio still taken for background."""
    open_size: float = 0.002
    """radius of the morphological opening (fraction of the image height; 0: off)."""
    close_size: float = 0.006
    """radius of the morphological closing (fraction of the image height; 0: off)."""
    fill_holes: bool = True
    """fill holes enclosed by a foreground component."""
    min_area: float = 0.0005
    """components smaller than this fraction of the image area are dropped."""
    multiview: bool = True
    """intersect each mask with the reprojection of the largest component of the visual hull
    carved from all views' masks.
    """
    min_views: int | None = None
    """voxels of that hull must be inside this many masks (None: C − 1, at least 2, so one view's
    miss does not remove the subject).
    """
    voxel_size: float = 0.03
    """hull voxel edge (metres)."""
    hull_dilation: float = 0.004
    """masks are dilated by this fraction of the image height before carving (tolerance for
    calibration error; the result is intersected with the undilated masks).
    """
    hull_margin: float = 0.2
    """the hull is carved in the box around the subject's triangulated keypoints padded by this
    many metres, and only within this distance of their neighbourhood graph (minimum spanning
    tree plus nearest neighbours: the limbs; a person beside the subject is not carved with
    it).
    """
    hull_extent: float = 1.5
    """without keypoints (or ``bounds``), half-size (metres) of the cube around the point the
    cameras look at.
    """
    bounds: tuple[tuple[float, float], ...] | None = None
    """``[[xmin, xmax], [ymin, ymax], [zmin, zmax]]`` world box (metres) for the hull, overriding
    both; None: automatic.
    """
    keypoint_gate: bool = True
    """keep only mask components that overlap the subject's 2D keypoint box (expanded by
    ``keypoint_margin``) in that view (needs keypoints; a view without keypoints is left as it
    is).
    """
    keypoint_margin: float = 0.15
    """box expansion as a fraction of the box's larger side."""
    min_confidence: float = 0.3
    """keypoints below this confidence are ignored (box, triangulation)."""

    def __post_init__(self) -> None:
        self._check("masks")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | MaskSettings | None = None,
                  prefix: str = "masks") -> MaskSettings:
        """Settings from a (Hydra) mapping; missing keys keep their defaults.

        Args:
            values: ``{name: value}`` (an ``omegaconf.DictConfig`` works), settings, or None.
            prefix: how errors name the keys (``data.masks`` → ``data.masks.threshold: ...``).

        Raises:
            MaskError: an unknown key (the known ones are listed) or a bad value.

        Example:
            >>> MaskSettings.from_dict({"scale": 0.5}).scale
            0.5
        """
        if values is None:
            return cls()
        if isinstance(values, MaskSettings):
            return values
        if not isinstance(values, Mapping):
            try:  # an omegaconf DictConfig is not a Mapping subclass everywhere
                values = dict(values)
            except (TypeError, ValueError):
                raise MaskError(f"{prefix}: expected a mapping of settings, got "
                                f"{type(values).__name__}") from None
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(map(str, values)) - known)
        if unknown:
            raise MaskError(f"{prefix}: unknown setting(s) {unknown}; expected some of "
                            f"{sorted(known)}")
        kw = dict(values)
        if kw.get("bounds") is not None:
            try:
                kw["bounds"] = tuple(tuple(float(v) for v in row) for row in kw["bounds"])
            except (TypeError, ValueError):
                raise MaskError(f"{prefix}.bounds: expected [[xmin, xmax], [ymin, ymax], "
                                f"[zmin, zmax]] in metres, got {kw['bounds']!r}") from None
        settings = object.__new__(cls)
        for f in fields(cls):
            object.__setattr__(settings, f.name, kw.get(f.name, getattr(cls, f.name)))
        settings._check(prefix)
        return settings

    def to_dict(self) -> dict[str, Any]:
        """The flat dict form (JSON/YAML safe; ``bounds`` as nested lists)."""
        d = asdict(self)
        if d["bounds"] is not None:
            d["bounds"] = [list(row) for row in d["bounds"]]
        return d

    def _check(self, prefix: str) -> None:
        def number(name: str, lo: float, hi: float = math.inf, lo_open: bool = True) -> None:
            v = getattr(self, name)
            ok = (not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
                  and (v > lo if lo_open else v >= lo) and v <= hi)
            if not ok:
                rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
                raise MaskError(f"{prefix}.{name}: expected a finite number in {rng}, got {v!r}")

        def integer(name: str, lo: int, allow_none: bool = False) -> None:
            v = getattr(self, name)
            if v is None and allow_none:
                return
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise MaskError(f"{prefix}.{name}: expected an integer >= {lo}"
                                f"{' or null' if allow_none else ''}, got {v!r}")

        def flag(name: str) -> None:
            if not isinstance(getattr(self, name), bool):
                raise MaskError(f"{prefix}.{name}: expected true or false, got "
                                f"{getattr(self, name)!r}")

        number("scale", 0.0, 1.0)
        integer("median_frames", 1)
        for name in ("register_plates", "plate_near_subject", "fill_holes", "multiview",
                     "keypoint_gate"):
            flag(name)
        number("max_plate_motion", 0.0, 0.5, lo_open=False)
        for name in ("plate_agreement", "threshold", "voxel_size", "hull_extent"):
            number(name, 0.0)
        number("min_noise", 0.0, 255.0)
        number("shadow_min", 0.0, 1.0, lo_open=False)
        number("highlight_max", 1.0, lo_open=False)
        for name in ("plate_dilation", "open_size", "close_size", "hull_dilation"):
            number(name, 0.0, 0.25, lo_open=False)
        number("min_area", 0.0, 1.0, lo_open=False)
        number("subject_radius", 0.0, 1.0)
        number("hull_margin", 0.0, lo_open=False)
        number("keypoint_margin", 0.0, lo_open=False)
        number("min_confidence", 0.0, lo_open=False)
        integer("min_views", 1, allow_none=True)
        if self.bounds is not None:
            b = self.bounds
            ok = (len(b) == 3 and all(len(r) == 2 and all(math.isfinite(v) for v in r)
                                      and r[0] < r[1] for r in b))
            if not ok:
                raise MaskError(f"{prefix}.bounds: expected [[xmin, xmax], [ymin, ymax], "
                                f"[zmin, zmax]] with min < max (metres), got {b!r}")
