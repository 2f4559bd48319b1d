"""Length unit of a motion file that does not state one, inferred from the subject's size.

BVH files carry no unit. A known skeleton family's map supplies it; for any other file the
reader measures the rest skeleton — the straightened ankle -> hip -> spine -> head-end chain of
:func:`~torchmocap.io.skeleton_maps.chain_height` (1.22-1.79 m for the adults of CMU and
HDM05), which needs the joints mapped onto human31 (by a map or by their names) — and picks the
common unit that makes it a person's: 0.75-1.95 m, from a small child to the tallest adults
(1.125-1.95 m counts as an adult). A skeleton that does not map onto human31 gets no guess.
The candidates differ by at least x2.2, and an adult's chain varies by about x1.25 either side
of 1.5 m, so one unit usually fits; where two do (a tall adult in CMU units is also a child in
inches, a small child in cm a giant in inches) the reading nearest an adult's 1.5 m is taken and
the others are reported (``UnitGuess.alternatives``) — pass the unit explicitly (``unit=`` /
``data.clip.unit``) for a child or a figure far from human size.

:func:`check_subject_size` measures a clip read in metres the same way and refuses one outside
a person's size (offsets in another unit than the one applied, or all zero), with a warning for
a child's size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["LENGTH_UNITS", "UnitGuess", "check_subject_size", "infer_length_unit"]

#: Common length units of motion files, metres per unit.
LENGTH_UNITS: dict[str, float] = {
    "m": 1.0,
    "CMU ASF unit (1/0.45 in)": 0.0254 / 0.45,
    "in": 0.0254,
    "cm": 0.01,
    "mm": 0.001,
}

#: Reference size in metres of the ankle-hip-head chain (geometric middle of 1.22-1.79 m).
_CHAIN_M = 1.5
#: a person's ankle-head chain in metres: a small child (~0.9 m tall) to the tallest adults
_PERSON = (0.75, 1.95)
#: the adults' part of that range (1.22-1.79 m measured for CMU and HDM05, with margin)
_ADULT_MIN = 1.125


@dataclass(frozen=True)
class UnitGuess:
    """Result of :func:`infer_length_unit`.

    Attributes:
        unit: metres per file unit (``None``: no guess).
        name: the unit's name in :data:`LENGTH_UNITS` (``None`` with ``unit``).
        size: the ankle-head chain in file units (``None`` when the joints do not map onto
            human31).
        alternatives: the other units of :data:`LENGTH_UNITS` that also give a person's size,
            as ``(name, metres per unit)`` pairs (empty when the guess is unambiguous).
    """

    unit: float | None
    name: str | None
    size: float | None
    alternatives: tuple[tuple[str, float], ...] = ()

    @property
    def child_sized(self) -> bool:
        """Whether the guess makes the subject smaller than an adult (a child, or a wrong unit)."""
        return self.unit is not None and self.size * self.unit < _ADULT_MIN

    def describe(self) -> str:
        if self.size is None:
            return "its joints do not map onto human31, so its size cannot be measured"
        if self.unit is None:
            return (f"its ankle-head chain measures {self.size:.4g} file units, which no common "
                    f"unit ({', '.join(LENGTH_UNITS)}) makes a person's size")
        text = (f"{self.unit:g} m per unit ({self.name}): its ankle-head chain measures "
                f"{self.size:.4g} units = {self.size * self.unit:.2f} m")
        if self.child_sized:
            text += ", a child's size"
        if self.alternatives:
            other = " or ".join(f"{self.size * u:.2f} m in {n}" for n, u in self.alternatives)
            text += f" (ambiguous: also {other})"
        return text


def infer_length_unit(clip, skeleton_map=None) -> UnitGuess:
    """Metres per unit of ``clip`` (read with unit 1), from the size of its rest skeleton.

    Args:
        clip: a :class:`~torchmocap.io.MotionClip` whose lengths are in file units.
        skeleton_map: the map to find ankle and head with (default: detected or guessed from
            the joint names).

    Returns:
        :class:`UnitGuess`; ``unit`` is ``None`` when the joints do not map onto human31 or no
        unit of :data:`LENGTH_UNITS` puts the chain within a person's 0.75-1.95 m.
    """
    from torchmocap.io.errors import SkeletonMapError
    from torchmocap.io.skeleton_maps import chain_height

    try:
        size = 0.5 * (chain_height(clip, skeleton_map, "left")
                      + chain_height(clip, skeleton_map, "right"))
    except SkeletonMapError:
        return UnitGuess(None, None, None)
    if not (math.isfinite(size) and size > 0):
        return UnitGuess(None, None, size)
    lo, hi = _PERSON
    fits = sorted(((n, u) for n, u in LENGTH_UNITS.items() if lo <= size * u <= hi),
                  key=lambda kv: abs(math.log(size * kv[1] / _CHAIN_M)))
    if not fits:
        return UnitGuess(None, None, size)
    (name, unit), *others = fits
    return UnitGuess(unit, name, size, tuple(others))


def check_subject_size(clip, skeleton_map=None, unit_setting: str = "unit") -> float | None:
    """The ankle-head chain (metres) of ``clip`` (read in metres), checked to be a person's.

    Args:
        clip: a :class:`~torchmocap.io.MotionClip` in metres (``clip.unit``: the metres per
            file unit that were applied).
        skeleton_map: the map to find ankle and head with (default: detected or guessed).
        unit_setting: the setting that chooses the unit, named in the error (e.g.
            ``data.clip.unit``).

    Returns:
        the chain in metres, or None when the joints do not map onto human31 (not measurable).

    Raises:
        MotionFormatError: the chain is outside a person's 0.75-1.95 m (the file's lengths are
            in another unit than the one applied, or its offsets are zero or corrupt) — naming
            the file, the size, the unit applied and ``unit_setting``.

    Warns:
        UserWarning: a child's size (below 1.125 m): right for a child, else a wrong unit.
    """
    import warnings

    from torchmocap.io.errors import MotionFormatError, SkeletonMapError
    from torchmocap.io.skeleton_maps import chain_height

    try:
        size = 0.5 * (chain_height(clip, skeleton_map, "left")
                      + chain_height(clip, skeleton_map, "right"))
    except SkeletonMapError:
        return None
    unit = getattr(clip, "unit", None)
    applied = "" if unit is None else f" with {unit:g} m per file unit"
    lo, hi = _PERSON
    if not (math.isfinite(size) and lo <= size <= hi):
        what = ("0 m: its offsets (bone lengths) are all zero" if size == 0
                else f"{_length(size)}{applied}")
        raise MotionFormatError(
            f"the subject's ankle-head chain measures {what}; a person's is {lo}-{hi} m (an "
            f"adult's {_ADULT_MIN}-{hi} m): the file's lengths are in another unit or corrupt "
            f"(set {unit_setting}: metres per file length unit)", clip.source_path)
    if size < _ADULT_MIN:
        warnings.warn(f"{clip.source_path}: the subject's ankle-head chain measures "
                      f"{size:.2f} m{applied}, a child's size; if the subject is an adult, set "
                      f"{unit_setting} (metres per file length unit)", stacklevel=2)
    return size


def _length(metres: float) -> str:
    """``metres`` in a readable unit (``1424 km``, ``3.2 mm``)."""
    if not math.isfinite(metres):
        return f"{metres} m"
    for unit, f in (("km", 1e3), ("m", 1.0), ("mm", 1e-3)):
        if abs(metres) >= f or unit == "mm":
            return f"{metres / f:.4g} {unit}"
    return f"{metres:.4g} m"
