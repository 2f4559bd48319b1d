"""Keypoint maps: where a 2D detector's keypoints sit on a skeleton.

A detector's keypoints are not the skeleton's joint centres: OpenPose's hips lie lateral of and
above the hip joint centres, its shoulders above the glenohumeral centres, and nose, eyes and
ears are points on the head. A :class:`KeypointMap` gives every mapped keypoint ``k`` the joint
it rides on (``joint``), the joint whose bone frame its offset is expressed in (``frame``: the
joint itself or its parent) and the offset ``o_k`` (metres) in that frame::

    x_k = p_joint(k) + R_frame(k) o_k                                   (keypoint_positions)

A map is a small YAML file (``torchmocap/conf/keypoint_map/<format>.yaml`` for the built-in
formats, or any path)::

    format: body_25b                # the detector's keypoint format
    skeleton: human31               # the skeleton preset the joints belong to
    keypoints: [Nose, LEye, ...]    # the format's K keypoints, in its column order
    map:                            # the K' mapped keypoints (the others are left out)
      Nose: {joint: head, offset: [0.0, -0.105, -0.03]}
      LShoulder: {joint: l_shoulder, frame: spine, offset: [0.0, 0.0, 0.04]}

At human31's zero pose every bone frame is the world frame: ``+x`` is the subject's left, ``-y``
forward, ``+z`` up. The ``frame`` of a keypoint is restricted to its joint or the joint's parent
so that the keypoint is a point of one rigid bone (:meth:`KeypointMap.attachment`): a fixed
child of the skeleton, which is how inverse kinematics fits keypoints
(:mod:`torchmocap.ik.keypoint_fit`).

Shapes: ``J`` joints, ``K`` keypoints of the format, ``K'`` mapped keypoints.

Example:
    >>> from torchmocap.skeleton import human31
    >>> sk = human31()
    >>> kmap = load_keypoint_map("body_25b", sk)
    >>> kin = sk(sk.zero_pose((2,)))
    >>> keypoint_positions(kin.positions, kin.rotations, kmap).shape
    torch.Size([2, 25, 3])
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import torch

from torchmocap.skeleton.skeleton import Skeleton

__all__ = [
    "KeypointMap",
    "KeypointMapError",
    "keypoint_positions",
    "known_keypoint_formats",
    "load_keypoint_map",
]


class KeypointMapError(ValueError):
    """A keypoint map is malformed, or does not fit the skeleton or the detections (names the
    file, keypoints or joints)."""


def _builtin_dir():
    return resources.files("torchmocap") / "conf" / "keypoint_map"


def known_keypoint_formats() -> list[str]:
    """Names of the built-in keypoint maps (``body_25``, ``body_25b``, ``coco_17``, ...)."""
    return sorted(p.name[:-5] for p in _builtin_dir().iterdir() if p.name.endswith(".yaml"))


@dataclass(frozen=True)
class KeypointMap:
    """The keypoints of one detector format on one skeleton (module docstring).

    Attributes:
        format: the keypoint format's name.
        format_keypoints: the format's ``K`` keypoint names in its column order.
        names: the ``K'`` mapped keypoints (in the format's order).
        joints: ``K'`` names of the joints they ride on.
        frames: ``K'`` names of the joints whose bone frames the offsets are expressed in.
        offsets: ``(K', 3)`` float64 offsets (metres).
        joint_index: ``(K',)`` int64 indices of ``joints`` in the skeleton.
        frame_index: ``(K',)`` int64 indices of ``frames`` in the skeleton.
        skeleton_joints: the joint names of the skeleton the map is bound to.
        origin: where the map was read from.
    """

    format: str
    format_keypoints: tuple[str, ...]
    names: tuple[str, ...]
    joints: tuple[str, ...]
    frames: tuple[str, ...]
    offsets: torch.Tensor
    joint_index: torch.Tensor
    frame_index: torch.Tensor
    skeleton_joints: tuple[str, ...]
    origin: str = ""

    @property
    def num_keypoints(self) -> int:
        """Number of mapped keypoints ``K'``."""
        return len(self.names)

    def columns(self, keypoint_names: Sequence[str], what: str = "keypoint_names"
                ) -> torch.Tensor:
        """``(K',)`` int64 positions of the mapped keypoints among ``keypoint_names`` (the
        columns of a detection array).

        Raises:
            KeypointMapError: a mapped keypoint is not among ``keypoint_names`` (names them).
        """
        where = {n: i for i, n in enumerate(keypoint_names)}
        missing = [n for n in self.names if n not in where]
        if missing:
            raise KeypointMapError(
                f"{what}: the {self.format!r} keypoint map needs keypoints {missing}, which "
                f"the detections do not have (they have {list(keypoint_names)})")
        return torch.tensor([where[n] for n in self.names], dtype=torch.long)

    def attachment(self, skeleton: Skeleton) -> tuple[list[int], torch.Tensor]:
        """Each keypoint as a fixed point of one bone: ``(bone joint indices (K',), offsets
        (K', 3))`` with ``x_k = p_bone + R_bone offset`` — the frame joint, with the rest offset
        of the riding joint from it added when the two differ (float64, at ``skeleton``'s own
        offsets; :meth:`attachment_offsets` for other offsets)."""
        self._check_skeleton(skeleton)
        rest = skeleton.offsets.detach().to(device="cpu", dtype=torch.float64)
        return self.frame_index.tolist(), self.attachment_offsets(rest)

    def attachment_offsets(self, rest_offsets: torch.Tensor) -> torch.Tensor:
        """``(K', 3)`` offsets of the keypoints from their frame joints (:meth:`attachment`)
        for the skeleton's rest offsets ``(J, 3)`` (differentiable in them)."""
        j, f = self.joint_index.to(rest_offsets.device), self.frame_index.to(rest_offsets.device)
        riding = rest_offsets.index_select(0, j) * (j != f)[:, None].to(rest_offsets)
        return self.offsets.to(rest_offsets) + riding

    def to_dict(self) -> dict:
        """The map in its YAML schema (``format``, ``keypoints``, ``map``; offsets as lists),
        JSON-safe: :func:`load_keypoint_map` reads it back (e.g. a subject's fitted map stored
        in a sequence's ``meta``)."""
        return {"format": self.format, "keypoints": list(self.format_keypoints),
                "map": {n: {"joint": j, "frame": f, "offset": [float(v) for v in o]}
                        for n, j, f, o in zip(self.names, self.joints, self.frames,
                                              self.offsets.tolist())}}

    def bind(self, skeleton: Skeleton) -> KeypointMap:
        """The same map resolved against another skeleton's joints (by name)."""
        return _resolve(self.format, self.format_keypoints,
                        {n: (j, f, o) for n, j, f, o in zip(self.names, self.joints, self.frames,
                                                            self.offsets.tolist())},
                        skeleton, self.origin)

    def _check_skeleton(self, skeleton: Skeleton) -> None:
        if tuple(skeleton.joint_names) != self.skeleton_joints:
            raise KeypointMapError(f"skeleton: the keypoint map is bound to joints "
                                   f"{list(self.skeleton_joints)}, got "
                                   f"{list(skeleton.joint_names)} (use KeypointMap.bind)")


def _resolve(fmt: str, keypoints: Sequence[str], entries: Mapping[str, tuple],
             skeleton: Skeleton, origin: str) -> KeypointMap:
    names = [k for k in keypoints if k in entries]
    index = {n: i for i, n in enumerate(skeleton.joint_names)}
    unknown = sorted({x for k in names for x in entries[k][:2] if x not in index})
    if unknown:
        raise KeypointMapError(f"{origin}: unknown joints {unknown} (skeleton "
                               f"{skeleton.name!r} has {list(skeleton.joint_names)})")
    ji = [index[entries[k][0]] for k in names]
    fi = [index[entries[k][1]] for k in names]
    for k, j, f in zip(names, ji, fi):
        if f != j and f != skeleton.parents[j]:
            raise KeypointMapError(
                f"{origin}: map.{k}: frame {skeleton.joint_names[f]!r} must be the joint "
                f"{skeleton.joint_names[j]!r} itself or its parent")
    return KeypointMap(
        format=fmt, format_keypoints=tuple(keypoints), names=tuple(names),
        joints=tuple(entries[k][0] for k in names), frames=tuple(entries[k][1] for k in names),
        offsets=torch.tensor([entries[k][2] for k in names], dtype=torch.float64).reshape(-1, 3),
        joint_index=torch.tensor(ji, dtype=torch.long),
        frame_index=torch.tensor(fi, dtype=torch.long),
        skeleton_joints=tuple(skeleton.joint_names), origin=origin)


def _parse(data, origin: str, skeleton: Skeleton | None) -> KeypointMap:
    if not isinstance(data, Mapping):
        raise KeypointMapError(f"{origin}: a keypoint map must be a YAML mapping")
    fmt = data.get("format")
    if not isinstance(fmt, str) or not fmt:
        raise KeypointMapError(f"{origin}: 'format' must be a non-empty string")
    keypoints = data.get("keypoints")
    if (not isinstance(keypoints, list) or not keypoints
            or not all(isinstance(k, str) and k for k in keypoints)):
        raise KeypointMapError(f"{origin}: 'keypoints' must list the format's keypoint names in "
                               "column order")
    dup = sorted({k for k in keypoints if keypoints.count(k) > 1})
    if dup:
        raise KeypointMapError(f"{origin}: keypoints {dup} are listed more than once")
    entries = data.get("map")
    if not isinstance(entries, Mapping) or not entries:
        raise KeypointMapError(f"{origin}: 'map' must map keypoint names to "
                               "{joint, offset[, frame]}")
    stray = [k for k in entries if k not in keypoints]
    if stray:
        raise KeypointMapError(f"{origin}: map: unknown keypoints {stray} (the format's "
                               f"keypoints are {keypoints})")
    parsed = {}
    for k, e in entries.items():
        if not isinstance(e, Mapping) or not isinstance(e.get("joint"), str):
            raise KeypointMapError(f"{origin}: map.{k}: expected {{joint: <name>, offset: "
                                   "[x, y, z]}}")
        extra = sorted(set(e) - {"joint", "frame", "offset"})
        if extra:
            raise KeypointMapError(f"{origin}: map.{k}: unknown keys {extra} (joint, frame, "
                                   "offset)")
        off = e.get("offset", [0.0, 0.0, 0.0])
        try:
            off = [float(v) for v in off]
        except (TypeError, ValueError):
            off = []
        if len(off) != 3 or not all(math.isfinite(v) for v in off):
            raise KeypointMapError(f"{origin}: map.{k}.offset: expected 3 finite numbers "
                                   f"(metres), got {e.get('offset')!r}")
        frame = e.get("frame", e["joint"])
        if not isinstance(frame, str):
            raise KeypointMapError(f"{origin}: map.{k}.frame: expected a joint name")
        parsed[k] = (e["joint"], frame, off)
    if skeleton is None:
        from torchmocap.skeleton.presets import PRESETS, preset

        name = data.get("skeleton", "human31")
        if name not in PRESETS:
            raise KeypointMapError(f"{origin}: skeleton: unknown preset {name!r} (known: "
                                   f"{list(PRESETS)}); pass the skeleton to bind the map to")
        skeleton = preset(name)
    return _resolve(fmt, keypoints, parsed, skeleton, origin)


def load_keypoint_map(name_or_path: str | Path | KeypointMap | Mapping,
                      skeleton: Skeleton | None = None) -> KeypointMap:
    """A built-in keypoint map by format name (case-insensitive: ``"BODY_25B"`` is
    ``body_25b``), or a map from a YAML path or its parsed content, bound to ``skeleton``.

    Args:
        name_or_path: format name, YAML path, a mapping in the YAML schema (e.g.
            :meth:`KeypointMap.to_dict`), or a :class:`KeypointMap` (re-bound).
        skeleton: the skeleton whose joints the keypoints ride on (default: the preset named
            by the map's ``skeleton`` key, human31).

    Raises:
        KeypointMapError: unknown format, unreadable or malformed YAML, or joints the skeleton
            does not have (the message names them).
    """
    if isinstance(name_or_path, KeypointMap):
        return name_or_path if skeleton is None else name_or_path.bind(skeleton)
    if isinstance(name_or_path, Mapping):
        return _parse(name_or_path, "keypoint map (mapping)", skeleton)
    import yaml

    from torchmocap.inputs import read_text_input, yaml_error_line

    s = str(name_or_path)
    if s.lower() in known_keypoint_formats():
        res = _builtin_dir() / f"{s.lower()}.yaml"
        text, origin = res.read_text(encoding="utf-8"), str(res)
    else:
        p = Path(s)
        if not (p.suffix.lower() in (".yaml", ".yml") or p.exists()):
            raise KeypointMapError(f"unknown keypoint format {s!r}; built-in formats: "
                                   f"{known_keypoint_formats()} (or pass the path of a map YAML)")
        text, origin = read_text_input(p, KeypointMapError, "keypoint map (YAML)"), str(p)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise KeypointMapError(f"{origin}: not valid YAML ({yaml_error_line(e)})") from None
    return _parse(data, origin, skeleton)


def keypoint_positions(positions: torch.Tensor, rotations: torch.Tensor, kmap: KeypointMap,
                       offsets: torch.Tensor | None = None) -> torch.Tensor:
    """World positions of the mapped keypoints, ``x_k = p_joint(k) + R_frame(k) o_k``.

    Args:
        positions: ``(..., J, 3)`` joint positions (metres).
        rotations: ``(..., J, 3, 3)`` joint (bone) frames, e.g. of
            :class:`~torchmocap.skeleton.Kinematics`.
        kmap: a :class:`KeypointMap` bound to the skeleton of the joints.
        offsets: optional ``(..., K', 3)`` offsets replacing ``kmap.offsets`` (broadcast
            against the batch; gradients flow into them).

    Returns:
        ``(..., K', 3)`` keypoint positions (differentiable in all inputs), in the dtype and on
        the device of ``positions``.

    Raises:
        ValueError: shapes that do not match the map's skeleton.
    """
    J, Kp = len(kmap.skeleton_joints), kmap.num_keypoints
    if positions.dim() < 2 or positions.shape[-2:] != (J, 3):
        raise ValueError(f"positions: expected shape (..., {J}, 3), got "
                         f"{tuple(positions.shape)}")
    if rotations.shape != (*positions.shape[:-1], 3, 3):
        raise ValueError(f"rotations: expected shape {(*positions.shape[:-1], 3, 3)}, got "
                         f"{tuple(rotations.shape)}")
    dev = positions.device
    o = kmap.offsets if offsets is None else offsets
    if o.shape[-2:] != (Kp, 3):
        raise ValueError(f"offsets: expected shape (..., {Kp}, 3), got {tuple(o.shape)}")
    o = o.to(dtype=positions.dtype, device=dev)
    p = positions.index_select(-2, kmap.joint_index.to(dev))
    R = rotations.index_select(-3, kmap.frame_index.to(dev))
    return p + (R @ o[..., None])[..., 0]
