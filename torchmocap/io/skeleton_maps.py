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
    "JointGuess",
    "SkeletonMap",
    "chain_height",
    "detect_family",
    "guess_joint_map",
    "guess_joints",
    "guessed_joints",
    "human31_positions",
    "joint_map_report",
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

    from torchmocap.inputs import yaml_error_line

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise SkeletonMapError(f"{origin}: not valid YAML ({yaml_error_line(e)})") from None


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
        from torchmocap.inputs import read_text_input

        text = read_text_input(p, SkeletonMapError, "skeleton map (YAML)")
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


# ------------------------------------------------------------------------- name guessing
# A source joint name is split into words ("mixamorig:LeftUpLeg" -> left, up, leg;
# "UpperArm_L" -> upper, arm, l; "thigh.L" -> thigh, l; "lShldr" -> l, shldr); side words
# (left/right/l/r) give the side, trailing numbers an index, "end"/"tip"/"nub" mark an end site
# ("Head_end"), a few decorations (jnt, bip01, mixamorig, def) are dropped, and the remaining
# words joined are the *core* ("upperarm", "upleg", "toebase") compared with the synonyms below.
_SIDE_WORDS = {"l": "l", "left": "l", "r": "r", "right": "r"}
_END_WORDS = {"end", "tip", "nub"}
_DECORATIONS = {"mixamorig", "bip", "jnt", "j", "bn", "bone", "def"}
_TORSO = {"spine", "chest", "torso", "abdomen", "waist", "back", "lowerback", "upperback",
          "midback", "middleback", "thorax", "upperchest", "trunk"}
_NECK = {"neck", "lowerneck", "neckbase", "upperneck"}
_CLAVICLE = {"clavicle", "collar", "collarbone", "scapula"}
# human31 limb joint -> tiers of cores; the first tier with a candidate decides (two different
# cores in that tier are ambiguous). "shoulder" is the upper-arm joint only when no upper-arm
# name exists (it is the clavicle in MotionBuilder/Mixamo skeletons, which have "Arm" too).
_LIMB_TIERS: dict[str, tuple[frozenset, ...]] = {
    "shoulder": (frozenset({"upperarm", "uparm", "arm", "humerus"}),
                 frozenset({"shoulder", "shldr"})),
    "elbow": (frozenset({"forearm", "lowerarm", "lowarm", "elbow", "radius", "ulna"}),),
    "wrist": (frozenset({"wrist"}), frozenset({"hand"})),
    "hand": (frozenset({"hand", "fingers", "handtip", "palm"}),
             frozenset({"middle", "mid", "handmiddle", "middlefinger", "finger", "fingerbase"})),
    "hip": (frozenset({"upleg", "upperleg", "thigh", "femur"}), frozenset({"hip"})),
    "knee": (frozenset({"lowerleg", "lowleg", "leg", "shin", "calf", "knee", "tibia", "shank",
                        "crus"}),),
    "ankle": (frozenset({"ankle"}), frozenset({"foot"})),
    "toe": (frozenset({"toebase", "toe", "toes", "ball", "forefoot"}), frozenset({"foot"})),
}
_KNOWN_CORES = (_TORSO | _NECK | _CLAVICLE | {"hips", "pelvis", "hip", "root", "head",
                                              "headtop"}
                | {c for tiers in _LIMB_TIERS.values() for t in tiers for c in t})
_WORD_RE = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+")


@dataclass(frozen=True)
class _Name:
    """A source joint name taken apart: side ("l", "r" or None), core, index, end-site flag."""

    name: str
    side: str | None
    core: str
    index: int
    is_end: bool


def _parse_name(name: str) -> _Name:
    base = name.rsplit(":", 1)[-1]  # namespaces: "mixamorig:LeftArm"
    words = [w.lower() for w in _WORD_RE.findall(base)]
    sides = {_SIDE_WORDS[w] for w in words if w in _SIDE_WORDS}
    side = sides.pop() if len(sides) == 1 else None
    words = [w for w in words if w not in _SIDE_WORDS]
    is_end = bool(words) and words[-1] in _END_WORDS
    if is_end:
        words = words[:-1]
    index = -1
    if words and words[-1].isdigit():
        index = int(words[-1])
    words = [w for w in words if not w.isdigit() and w not in _DECORATIONS]
    core = "".join(words)
    if side is None and not sides and core not in _KNOWN_CORES:
        # one lower-case word: "lfemur", "rtoes", "upperarml" (a known core with a side letter)
        for pre, sd in (("left", "l"), ("right", "r"), ("l", "l"), ("r", "r")):
            if core.startswith(pre) and core[len(pre):] in _KNOWN_CORES:
                side, core = sd, core[len(pre):]
                break
            if core.endswith(pre) and core[:-len(pre)] in _KNOWN_CORES:
                side, core = sd, core[:-len(pre)]
                break
    return _Name(name, side, core, index, is_end)


@dataclass(frozen=True)
class JointGuess:
    """The result of :func:`guess_joints`.

    Attributes:
        joints: human31 joint -> source joint name, for every joint that could be guessed.
        missing: human31 joints without any candidate.
        ambiguous: human31 joint -> its candidate source joints (two or more: refused).
    """

    joints: dict[str, str]
    missing: tuple[str, ...]
    ambiguous: dict[str, tuple[str, ...]]

    @property
    def complete(self) -> bool:
        return not self.missing and not self.ambiguous


def _structure(clip_or_names, names: list[str]):
    """Parents and rest positions of a clip (``None`` for plain names)."""
    parents = getattr(clip_or_names, "parents", None)
    offsets = getattr(clip_or_names, "offsets", None)
    if parents is None or offsets is None:
        return None, None
    pos = [None] * len(names)
    off = offsets.detach().to(torch.float64).cpu()
    for j, p in enumerate(parents):
        pos[j] = off[j] if p < 0 else pos[p] + off[j]
    return list(parents), torch.stack(pos)


def guess_joints(clip_or_names) -> JointGuess:
    """Guess which source joint plays each human31 joint from the names alone.

    Understands the common side conventions — ``LeftArm``/``RightArm``, ``LArm``, ``l_arm``,
    ``Arm_L``, ``arm.L``, ``ArmL``, ``lhumerus``, ``mixamorig:`` and other ``namespace:``
    prefixes, any case — and limb synonyms: upper arm / arm / humerus (shoulder joint),
    forearm / lower arm, wrist / hand, upper leg / up leg / thigh / femur (hip joint), lower leg
    / leg / shin / calf / knee, ankle / foot, toe / toes / toe base / ball, hips / pelvis / hip
    / root, spine / chest / torso / abdomen / back (the first torso joint above the pelvis),
    neck (the lowest neck joint), head, and the head's end site for ``head_top`` (the hand's
    end site or a middle finger for ``l_hand``, the foot's for ``l_toe``). An end site of zero
    length (at its parent's position) is used only when nothing else qualifies, as the built-in
    CMU21 map does. When two *different* names qualify for one human31 joint (say
    ``Arm_L`` and ``UpperArm_L``) the joint is reported as ambiguous with both candidates rather
    than picked.

    Args:
        clip_or_names: a :class:`MotionClip` (its hierarchy breaks ties along chains and drops
            zero-length end sites) or a list of joint names.
    """
    names = _names_of(clip_or_names)
    parsed = [_parse_name(n) for n in names]
    parents, pos = _structure(clip_or_names, names)
    kids = [0] * len(names)
    if parents is not None:
        for p in parents:
            if p >= 0:
                kids[p] += 1

    def degenerate(i: int) -> bool:
        # a leaf at its parent's position (a zero-length end site) is a last resort
        return (pos is not None and kids[i] == 0 and parents[i] >= 0
                and float(pos[i].sub(pos[parents[i]]).norm()) < 1e-9)

    zero = [degenerate(i) for i in range(len(names))]
    out: dict[str, str] = {}
    ambiguous: dict[str, tuple[str, ...]] = {}
    used: set[int] = set()

    def pick(h: str, cands: list[int], chain: bool = False) -> int | None:
        cands = [i for i in cands if i not in used]
        cands = [i for i in cands if not zero[i]] or cands
        if not cands:
            return None
        cores = {parsed[i].core for i in cands}
        if len(cores) > 1 and not chain:
            ambiguous[h] = tuple(names[i] for i in cands)
            return None
        if len(cands) > 1 and not chain:
            # one core several times: a chain ("Mid1, Mid2") picks its first, else ambiguous
            on_chain = parents is not None and all(
                _is_ancestor(parents, a, b) for a, b in zip(cands[:-1], cands[1:]))
            by_index = len({parsed[i].index for i in cands}) == len(cands)
            if not (on_chain or (parents is None and by_index)):
                ambiguous[h] = tuple(names[i] for i in cands)
                return None
            cands = sorted(cands, key=lambda i: (parsed[i].index, i)) if parents is None \
                else cands
        i = cands[0]
        out[h] = names[i]
        used.add(i)
        return i

    def find(cores, side=None, end=False, sided=None) -> list[int]:
        return [i for i, n in enumerate(parsed)
                if n.core in cores and n.is_end == end
                and (n.side == side if sided is None else (n.side is not None) == sided)]

    # torso: pelvis, spine, neck, head, head top (no side)
    pelvis = pick("pelvis", find({"hips", "pelvis", "hip"}) or find({"root"}))
    neck = pick("neck", find(_NECK), chain=True)
    torso = find(_TORSO)
    if pos is not None and pelvis is not None:  # first torso joint clearly above the pelvis
        rise = [float((pos[i] - pos[pelvis]).norm()) for i in torso]
        ref = float((pos[neck] - pos[pelvis]).norm()) if neck is not None else max(rise or [0])
        torso = [i for i, r in zip(torso, rise) if r > 0.02 * ref] or torso
    pick("spine", torso, chain=True)
    head = pick("head", find({"head"}))
    pick("head_top", find({"headtop"}) + find({"headtop"}, end=True)
         or [i for i in find({"head"}, end=True)
             if parents is None or head is None or parents[i] == head])
    # limbs, per side
    for sd in ("l", "r"):
        def tiers(kind: str, extra: list[int] | None = None, sd: str = sd) -> list[int]:
            for t in _LIMB_TIERS[kind]:
                c = [i for i in find(t, side=sd) if i not in used]
                if c:
                    return c
            return extra or []

        pick(f"{sd}_shoulder", tiers("shoulder"))
        pick(f"{sd}_elbow", tiers("elbow"))
        wrist = pick(f"{sd}_wrist", tiers("wrist"))
        hand_end = [i for i in find({"hand", "wrist"}, side=sd, end=True)
                    if parents is None or parents[i] == wrist]
        pick(f"{sd}_hand", hand_end or tiers("hand"), chain=True)
        pick(f"{sd}_hip", tiers("hip"))
        pick(f"{sd}_knee", tiers("knee"))
        ankle = pick(f"{sd}_ankle", tiers("ankle"))
        toe_end = [i for i in find({"foot", "ankle"}, side=sd, end=True)
                   if parents is None or parents[i] == ankle]
        pick(f"{sd}_toe", tiers("toe", toe_end))
    missing = tuple(h for h in HUMAN31_JOINTS if h not in out and h not in ambiguous)
    return JointGuess({h: out[h] for h in HUMAN31_JOINTS if h in out}, missing,
                      {h: ambiguous[h] for h in HUMAN31_JOINTS if h in ambiguous})


def _is_ancestor(parents: list[int], a: int, b: int) -> bool:
    while b >= 0:
        b = parents[b]
        if b == a:
            return True
    return False


def guess_joint_map(clip_or_names) -> dict[str, str]:
    """human31 -> source names guessed from the names (:func:`guess_joints`); joints that are
    missing or ambiguous are left out."""
    return guess_joints(clip_or_names).joints


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
    names: Sequence[str], missing: Sequence[str], what: str, taken: Iterable[str] = (),
    ambiguous: Mapping[str, Sequence[str]] | None = None,
) -> SkeletonMapError:
    ambiguous = dict(ambiguous or {})
    bad = [h for h in HUMAN31_JOINTS if h in set(missing) | set(ambiguous)]
    lines = [f"{what}: cannot map {len(bad)} human31 joint(s): {bad}"]
    for h in bad:
        if h in ambiguous:
            lines.append(f"  {h}: ambiguous, candidates {list(ambiguous[h])}")
        else:
            lines.append(
                f"  {h}: closest source joints {_suggestions(h, names, taken) or '(none)'}")
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


_resolve = resolve_skeleton_map  # kept: torchmocap.data.subjects.mocap imports this name


def unmapped_joints(clip, skeleton_map: str | Path | SkeletonMap | None = None) -> list[str]:
    """human31 joints that the clip's map (or, without one, name guessing) cannot provide
    (missing or ambiguous names)."""
    names = set(_names_of(clip))
    smap = resolve_skeleton_map(clip, skeleton_map)
    if smap is None:
        g = guess_joints(clip)
        return [h for h in HUMAN31_JOINTS if h not in g.joints]
    return [h for h in HUMAN31_JOINTS if smap.joints.get(h) not in names]


def joint_map_report(clip, skeleton_map: str | Path | SkeletonMap | None = None
                     ) -> dict[str, object]:
    """How ``clip``'s joints map onto human31, as plain data (``torchmocap-info`` prints it).

    Returns:
        ``{"source": "skeleton_map" | "guessed", "family": str | None,
        "joints": {human31: source name or None}, "guessed_joints": [human31 names whose source
        was guessed from the names], "unmapped_joints": [...], "ambiguous": {human31:
        [candidates]}}``.
    """
    names = set(_names_of(clip))
    smap = resolve_skeleton_map(clip, skeleton_map)
    if smap is None:
        g = guess_joints(clip)
        return {"source": "guessed", "family": None,
                "joints": {h: g.joints.get(h) for h in HUMAN31_JOINTS},
                "guessed_joints": list(g.joints),
                "unmapped_joints": [h for h in HUMAN31_JOINTS if h not in g.joints],
                "ambiguous": {h: list(v) for h, v in g.ambiguous.items()}}
    joints = {h: (smap.joints.get(h) if smap.joints.get(h) in names else None)
              for h in HUMAN31_JOINTS}
    return {"source": "skeleton_map", "family": smap.family, "joints": joints,
            "guessed_joints": [], "unmapped_joints": [h for h, v in joints.items() if v is None],
            "ambiguous": {}}


def guessed_joints(clip, skeleton_map: str | Path | SkeletonMap | None = None) -> list[str]:
    """human31 joints whose source joint :func:`map_joints` takes from name guessing (all of
    them when no skeleton map applies, none with a map)."""
    if resolve_skeleton_map(clip, skeleton_map) is not None:
        return []
    return list(guess_joints(clip).joints)


def map_joints(clip, skeleton_map: str | Path | SkeletonMap | None = None) -> dict[str, int]:
    """human31 joint -> index of its source joint in ``clip``, for every human31 joint.

    Without a skeleton map the correspondence is guessed from the joint names
    (:func:`guess_joints`; :func:`guessed_joints` says when).

    Raises:
        SkeletonMapError: no map matches and name guessing leaves joints unmapped or ambiguous
            (listing the candidates, or the closest source names and how to write a map), or
            the map names joints the clip lacks.
    """
    names = _names_of(clip)
    smap = resolve_skeleton_map(clip, skeleton_map)
    what = getattr(clip, "source_path", None) or "skeleton"
    if smap is None:
        g = guess_joints(clip)
        if not g.complete:
            raise _unmappable_error(
                names, g.missing, f"{what} (no skeleton map matches; joint names guessed)",
                g.joints.values(), g.ambiguous,
            )
        return {h: names.index(g.joints[h]) for h in HUMAN31_JOINTS}
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
