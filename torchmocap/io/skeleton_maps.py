"""Skeleton maps: which joint of a motion file plays which human31 joint.

A map is a small YAML file (``torchmocap/conf/skeleton_map/<family>.yaml`` for the built-in
families; any path for a user's own, see ``docs/skeleton_maps.md``)::

    family: cmu_mb            # name of the skeleton family
    format: bvh               # optional: only files of this format match (bvh | asf)
    unit: 0.0564444           # optional: metres per file length unit, when the file can't say
    detect: [Hips, LHipJoint, LeftUpLeg]   # all must be joint names of a matching file
    filename_pattern: null    # optional fnmatch pattern on the file name (tie-breaker)
    joints:                   # human31 joint -> source joint (positions)
      pelvis: Hips
      ...
    bones:                    # optional: human31 joint -> source joint whose frame is that bone
      l_knee: LeftLeg

:func:`detect_family` picks the most specific map whose ``detect`` names all occur in a clip;
:func:`map_joints` resolves a map on a clip; an unmappable skeleton raises
:class:`SkeletonMapError` listing the human31 joints it lacks with the closest source names.
"""

from __future__ import annotations

import difflib
import fnmatch
import functools
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import torch

from torchmocap.io.errors import SkeletonMapError

__all__ = [
    "HUMAN31_JOINTS",
    "SkeletonMap",
    "chain_height",
    "detect_family",
    "guess_joint_map",
    "human31_positions",
    "known_families",
    "load_skeleton_map",
    "map_joints",
    "resolve_skeleton_map",
    "unmapped_joints",
]

#: human31 joint names (docs/skeleton_api.md), in the preset's order.
HUMAN31_JOINTS: tuple[str, ...] = (
    "pelvis",
    "spine",
    "neck",
    "head",
    "head_top",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
    "l_hand",
    "r_shoulder",
    "r_elbow",
    "r_wrist",
    "r_hand",
    "l_hip",
    "l_knee",
    "l_ankle",
    "l_toe",
    "r_hip",
    "r_knee",
    "r_ankle",
    "r_toe",
)


@dataclass(frozen=True)
class SkeletonMap:
    """One skeleton family's correspondence to human31 (see the module docstring)."""

    family: str
    joints: Mapping[str, str]
    unit: float | None = None
    detect: tuple[str, ...] = ()
    source_format: str | None = None
    filename_pattern: str | None = None
    bones: Mapping[str, str] = field(default_factory=dict)
    description: str = ""
    origin: str | None = None

    def matches(
        self, names: Iterable[str], source_format: str | None = None, path: str | None = None
    ) -> bool:
        """Whether a file with these joint names (and format, path) belongs to this family."""
        if not self.detect:
            return False
        names = set(names)
        if not all(d in names for d in self.detect):
            return False
        if self.source_format and source_format and self.source_format != source_format:
            return False
        if self.filename_pattern:
            return path is not None and fnmatch.fnmatch(Path(path).name, self.filename_pattern)
        return True


#: user maps loaded from YAML paths in this session, by family name
_USER_MAPS: dict[str, SkeletonMap] = {}


def _builtin_dir():
    return resources.files("torchmocap") / "conf" / "skeleton_map"


def known_families() -> list[str]:
    """Names of the built-in skeleton maps."""
    return sorted(p.name[:-5] for p in _builtin_dir().iterdir() if p.name.endswith(".yaml"))


def _close(name: str, options: Iterable[str], n: int = 3) -> list[str]:
    options = list(options)
    low = {o.lower(): o for o in options}
    hits = difflib.get_close_matches(name.lower(), list(low), n=n, cutoff=0.4)
    return [low[h] for h in hits]


def _parse_map(data, origin: str) -> SkeletonMap:
    if not isinstance(data, Mapping):
        raise SkeletonMapError(f"{origin}: a skeleton map must be a YAML mapping")
    family = data.get("family")
    if not isinstance(family, str) or not family:
        raise SkeletonMapError(f"{origin}: 'family' must be a non-empty string")
    joints = data.get("joints")
    if not isinstance(joints, Mapping) or not joints:
        raise SkeletonMapError(f"{origin}: 'joints' must map human31 joint names to source names")
    for section in ("joints", "bones"):
        sec = data.get(section) or {}
        if not isinstance(sec, Mapping):
            raise SkeletonMapError(f"{origin}: '{section}' must be a mapping")
        for k, v in sec.items():
            if k not in HUMAN31_JOINTS:
                raise SkeletonMapError(
                    f"{origin}: {section}: {k!r} is not a human31 joint "
                    f"(closest: {_close(str(k), HUMAN31_JOINTS)}; all: {list(HUMAN31_JOINTS)})"
                )
            if not isinstance(v, str) or not v:
                raise SkeletonMapError(f"{origin}: {section}.{k} must be a source joint name")
    unit = data.get("unit")
    if unit is not None:
        try:
            unit = float(unit)
        except (TypeError, ValueError):
            raise SkeletonMapError(f"{origin}: 'unit' must be metres per file unit") from None
        if not (math.isfinite(unit) and unit > 0):
            raise SkeletonMapError(f"{origin}: 'unit' must be positive, got {unit}")
    detect = data.get("detect") or []
    if (
        not isinstance(detect, Sequence)
        or isinstance(detect, str)
        or not all(isinstance(d, str) for d in detect)
    ):
        raise SkeletonMapError(f"{origin}: 'detect' must be a list of joint names")
    fmt = data.get("format")
    if fmt not in (None, "bvh", "asf"):
        raise SkeletonMapError(f"{origin}: 'format' must be bvh, asf or absent, got {fmt!r}")
    return SkeletonMap(
        family=family,
        joints=dict(joints),
        unit=unit,
        detect=tuple(detect),
        source_format=fmt,
        filename_pattern=data.get("filename_pattern"),
        bones=dict(data.get("bones") or {}),
        description=str(data.get("description") or ""),
        origin=origin,
    )


def _read_yaml(text: str, origin: str):
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise SkeletonMapError(f"{origin}: not valid YAML ({e})") from None


@functools.cache
def _load_builtin(name: str) -> SkeletonMap:
    res = _builtin_dir() / f"{name}.yaml"
    return _parse_map(_read_yaml(res.read_text(encoding="utf-8"), str(res)), str(res))


def load_skeleton_map(name_or_path: str | Path | SkeletonMap) -> SkeletonMap:
    """A built-in map by family name (``"cmu_mb"``), or a user map from a YAML path.

    A user map loaded from a path is remembered under its family name for this session, so
    clips read with it (``clip.skeleton_family``) resolve it again by name.

    Raises:
        SkeletonMapError: unknown name, unreadable or malformed YAML.
    """
    if isinstance(name_or_path, SkeletonMap):
        return name_or_path
    s = str(name_or_path)
    if s in known_families():
        return _load_builtin(s)
    if s in _USER_MAPS:
        return _USER_MAPS[s]
    p = Path(s)
    if p.suffix.lower() in (".yaml", ".yml") or p.exists():
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as e:
            raise SkeletonMapError(f"{p}: cannot read skeleton map ({e.strerror or e})") from None
        m = _parse_map(_read_yaml(text, str(p)), str(p))
        if m.family in known_families():
            raise SkeletonMapError(
                f"{p}: family {m.family!r} is a built-in map's name; choose another name"
            )
        _USER_MAPS[m.family] = m  # later lookups by family name (clip.skeleton_family) find it
        return m
    raise SkeletonMapError(
        f"unknown skeleton map {s!r}; built-in families: {known_families()} "
        "(or pass the path of a map YAML, see docs/skeleton_maps.md)"
    )


def _names_of(clip_or_names) -> list[str]:
    return list(getattr(clip_or_names, "joint_names", clip_or_names))


def detect_family(
    clip_or_names,
    source_format: str | None = None,
    path: str | None = None,
    maps: Iterable[str | Path | SkeletonMap] = (),
) -> str | None:
    """Family of the most specific matching map, or ``None``.

    Args:
        clip_or_names: a :class:`MotionClip` (its format and path are used) or joint names.
        source_format, path: for plain names: file format (``"bvh"``/``"asf"``) and file path.
        maps: extra (user) maps to consider beside the built-in ones; they win ties. Maps
            loaded earlier from a YAML path in this session are considered too.

    Specificity: a map whose ``filename_pattern`` matched beats one without, then the longer
    ``detect`` list wins (the CMU MotionBuilder map lists more names than CMU21's, which are a
    subset of them).
    """
    names = _names_of(clip_or_names)
    source_format = source_format or getattr(clip_or_names, "source_format", None)
    path = path or getattr(clip_or_names, "source_path", None)
    candidates = [load_skeleton_map(m) for m in maps] + [_load_builtin(f) for f in known_families()]
    candidates += [m for m in _USER_MAPS.values() if m not in candidates]
    best, best_key = None, None
    for rank, m in enumerate(candidates):
        if m.matches(names, source_format, path):
            key = (m.filename_pattern is not None, len(m.detect), -rank)
            if best_key is None or key > best_key:
                best, best_key = m, key
    return None if best is None else best.family


def guess_joint_map(clip_or_names) -> dict[str, str]:
    """Best-effort human31 -> source names by exact (case-insensitive) match with any name the
    built-in maps use for that joint, each source joint used once (so DAZ's ``head_top: head``
    cannot turn a plain ``Head`` into the head top); the joints left out are unmappable."""
    names = _names_of(clip_or_names)
    low = {n.lower(): n for n in names}
    out: dict[str, str] = {}
    for h in HUMAN31_JOINTS:
        aliases = [h] + [_load_builtin(f).joints.get(h, "") for f in known_families()]
        for a in aliases:
            src = low.get(a.lower()) if a else None
            if src is not None and src not in out.values():  # one human31 joint per source
                out[h] = src
                break
    return out


_SIDE_RE = re.compile(r"^(?:[Ll]eft|[Ll](?=[_A-Z.]))|[_.][Ll]$")
_RSIDE_RE = re.compile(r"^(?:[Rr]ight|[Rr](?=[_A-Z.]))|[_.][Rr]$")


def _side(name: str) -> str | None:
    if _SIDE_RE.search(name):
        return "l"
    if _RSIDE_RE.search(name):
        return "r"
    return None


def _norm(name: str) -> str:
    n = re.sub(r"(?i)left", "l", re.sub(r"(?i)right", "r", name))
    return re.sub(r"[^0-9a-z]", "", n.lower())


def _name_score(alias: str, source: str) -> float:
    """Similarity of a known spelling of a human31 joint and a source joint name."""
    a, s = _norm(alias), _norm(source)
    sa, ss = _side(alias), _side(source)
    core = a[1:] if sa and a[:1] == sa else a
    score = difflib.SequenceMatcher(None, a, s).ratio()
    if core and core in s:
        score += 0.5
    if sa and ss and sa != ss:
        score -= 1.0
    return score


def _suggestions(h: str, names: Sequence[str], taken: Iterable[str] = (), n: int = 3) -> list[str]:
    taken = set(taken)
    aliases = {h} | {
        _load_builtin(f).joints[h] for f in known_families() if h in _load_builtin(f).joints
    }
    hs = h[0] if h[:2] in ("l_", "r_") else None
    scored = []
    for s in names:
        if s in taken:
            continue
        sc = max(_name_score(a, s) for a in aliases)
        if hs and _side(s) not in (None, hs):
            sc -= 1.0
        scored.append((sc, s))
    scored.sort(key=lambda x: -x[0])
    return [s for sc, s in scored[:n] if sc > 0.5]


def _unmappable_error(
    names: Sequence[str], missing: Sequence[str], what: str, taken: Iterable[str] = ()
) -> SkeletonMapError:
    lines = [f"{what}: cannot map {len(missing)} human31 joint(s): {list(missing)}"]
    for h in missing:
        lines.append(f"  {h}: closest source joints {_suggestions(h, names, taken) or '(none)'}")
    lines.append(
        "Write a skeleton map YAML (family, unit, detect, joints: {human31_name: source_name}; "
        "see docs/skeleton_maps.md) and pass it as skeleton_map=PATH."
    )
    return SkeletonMapError("\n".join(lines))


def resolve_skeleton_map(
    clip, skeleton_map: str | Path | SkeletonMap | None = None
) -> SkeletonMap | None:
    """The map to use for ``clip``: ``skeleton_map`` if given, else the clip's family, else the
    detected one; ``None`` when nothing matches."""
    if skeleton_map is not None:
        return load_skeleton_map(skeleton_map)
    fam = getattr(clip, "skeleton_family", None) or detect_family(clip)
    return None if fam is None else load_skeleton_map(fam)


_resolve = resolve_skeleton_map  # kept: torchmocap.data.subject imports this name


def unmapped_joints(clip, skeleton_map: str | Path | SkeletonMap | None = None) -> list[str]:
    """human31 joints that the clip's map (or, without one, name guessing) cannot provide."""
    names = set(_names_of(clip))
    smap = resolve_skeleton_map(clip, skeleton_map)
    if smap is None:
        guessed = guess_joint_map(clip)
        return [h for h in HUMAN31_JOINTS if h not in guessed]
    return [h for h in HUMAN31_JOINTS if smap.joints.get(h) not in names]


def map_joints(clip, skeleton_map: str | Path | SkeletonMap | None = None) -> dict[str, int]:
    """human31 joint -> index of its source joint in ``clip``, for every human31 joint.

    Raises:
        SkeletonMapError: no map matches (listing what name guessing cannot map, with the
            closest source names and how to write a map), or the map names joints the clip
            lacks.
    """
    names = _names_of(clip)
    smap = resolve_skeleton_map(clip, skeleton_map)
    what = getattr(clip, "source_path", None) or "skeleton"
    if smap is None:
        guessed = guess_joint_map(clip)
        missing = [h for h in HUMAN31_JOINTS if h not in guessed]
        if missing:
            raise _unmappable_error(
                names, missing, f"{what} (no skeleton map matches)", guessed.values()
            )
        return {h: names.index(guessed[h]) for h in HUMAN31_JOINTS}
    missing = [h for h in HUMAN31_JOINTS if smap.joints.get(h) not in names]
    if missing:
        taken = [v for k, v in smap.joints.items() if k not in missing]
        raise _unmappable_error(names, missing, f"{what} with map {smap.family!r}", taken)
    return {h: names.index(smap.joints[h]) for h in HUMAN31_JOINTS}


def human31_positions(clip, skeleton_map: str | Path | SkeletonMap | None = None) -> torch.Tensor:
    """World positions ``(T, 21, 3)`` of the human31 joints (in :data:`HUMAN31_JOINTS` order)."""
    idx = map_joints(clip, skeleton_map)
    return clip.global_positions()[:, [idx[h] for h in HUMAN31_JOINTS]]


def chain_height(
    clip, skeleton_map: str | Path | SkeletonMap | None = None, side: str = "left"
) -> float:
    """Straightened ankle -> hip -> spine -> head-end chain length in metres.

    The sum of the rest bone lengths along the skeleton tree path from the mapped ``l_ankle``
    (or ``r_ankle``) to ``head_top``: shank, thigh, hip offset, spine and neck segments, head.
    Foot and anything above the head end are excluded. A size check independent of pose.
    """
    if side not in ("left", "right"):
        raise ValueError(f"side: expected 'left' or 'right', got {side!r}")
    idx = map_joints(clip, skeleton_map)
    a = idx["l_ankle" if side == "left" else "r_ankle"]
    b = idx["head_top"]
    path = clip.path_between(a, b)
    total = 0.0
    for u, v in zip(path[:-1], path[1:]):
        child = u if clip.parents[u] == v else v
        total += float(clip.offsets[child].norm())
    return total
