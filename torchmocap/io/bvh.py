"""BVH (Biovision hierarchy) reader and writer.

Reader: any joint may have its own channel order; 3 or 6 channels (any subset of
``{X,Y,Z}{position,rotation}``, each at most once); position channels below the root give a
per-frame translation that replaces the joint's OFFSET; ``End Site`` blocks become 0-DoF leaf
joints named ``<parent>_end``. Lengths are multiplied by ``unit`` (metres per file unit): pass
it, or let the file's skeleton family (:mod:`torchmocap.io.skeleton_maps`) supply it, or else
the subject's size (:mod:`torchmocap.io.units`). Y-up files
are turned Z-up (``(x, y, z) -> (x, -z, y)``). Rotation channels ``Zrotation Xrotation Yrotation``
mean ``L = Rz(z) @ Rx(x) @ Ry(y)`` (the channel order is the matrix product order).

Writer: :func:`write_bvh` writes any :class:`MotionClip` (also one built from a human31 track
with :meth:`MotionClip.from_skeleton`), atomically (temp file + rename).
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchmocap.atomic import write_text_atomic
from torchmocap.io._euler import angles_to_matrix, matrix_to_angles
from torchmocap.io.errors import MotionFormatError
from torchmocap.io.motion import MotionClip, y_up_to_z_up, z_up_to_y_up

__all__ = ["read_bvh", "write_bvh", "parse_bvh"]

_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
_CHANNEL_RE = re.compile(r"^([xyz])(position|rotation)$", re.IGNORECASE)
_FRAMES_RE = re.compile(r"^frames\s*:?\s*(\S+)\s*$", re.IGNORECASE)
#: Plausible BVH frame times (seconds): 100 kHz to one frame a minute. ``Frame Time: 1e300``
#: would otherwise be a clip at 1e-300 fps (0.0 in a report) that nothing can use.
MIN_FRAME_TIME = 1e-5
MAX_FRAME_TIME = 60.0
_FRAME_TIME_RE = re.compile(r"^frame\s+time\s*:?\s*(\S+)\s*$", re.IGNORECASE)


@dataclass
class _Joint:
    name: str
    parent: int
    line: int
    offset: list[float] | None = None
    channels: list[str] = field(default_factory=list)
    end_site: bool = False


def _zup_axis(c: str) -> torch.Tensor:
    e = torch.zeros(3, dtype=torch.float64)
    e[_AXIS_INDEX[c]] = 1.0
    return y_up_to_z_up(e)


class _Tokens:
    """Whitespace tokens of the hierarchy lines, each with its 1-based line number."""

    def __init__(self, lines: list[str], path: str):
        self.items: list[tuple[str, int]] = []
        for ln, text in enumerate(lines, start=1):
            for tok in text.replace("{", " { ").replace("}", " } ").split():
                self.items.append((tok, ln))
        self.i = 0
        self.path = path
        self.last_line = len(lines)

    def peek(self) -> tuple[str, int] | None:
        return self.items[self.i] if self.i < len(self.items) else None

    def next(self, what: str) -> tuple[str, int]:
        if self.i >= len(self.items):
            raise MotionFormatError(
                f"unexpected end of HIERARCHY, expected {what}", self.path, self.last_line
            )
        self.i += 1
        return self.items[self.i - 1]

    def expect(self, word: str) -> int:
        tok, ln = self.next(repr(word))
        if tok.upper() != word.upper():
            raise MotionFormatError(f"expected {word!r}, found {tok!r}", self.path, ln)
        return ln

    def rest_of_line(self, ln: int) -> list[str]:
        out = []
        while (
            self.i < len(self.items)
            and self.items[self.i][1] == ln
            and self.items[self.i][0] != "{"
        ):
            out.append(self.items[self.i][0])
            self.i += 1
        return out

    def number(self, what: str) -> float:
        tok, ln = self.next(what)
        try:
            v = float(tok)
        except ValueError:
            raise MotionFormatError(
                f"expected a number for {what}, found {tok!r}", self.path, ln
            ) from None
        if not math.isfinite(v):
            raise MotionFormatError(f"{what} is not finite ({tok})", self.path, ln)
        return v


def _parse_hierarchy(lines: list[str], path: str) -> list[_Joint]:
    tk = _Tokens(lines, path)
    tk.expect("HIERARCHY")
    tok, ln = tk.next("ROOT")
    if tok.upper() != "ROOT":
        raise MotionFormatError(f"expected 'ROOT', found {tok!r}", path, ln)
    joints: list[_Joint] = []
    names: set[str] = set()

    def open_joint(parent: int, ln: int, end_site: bool) -> int:
        if end_site:
            if parent < 0:
                raise MotionFormatError("End Site cannot be the root", path, ln)
            base = f"{joints[parent].name}_end"
            name, k = base, 1
            while name in names:
                name, k = f"{base}{k}", k + 1
        else:
            parts = tk.rest_of_line(ln)
            if not parts:
                raise MotionFormatError("joint without a name", path, ln)
            name = " ".join(parts)
            if name in names:
                raise MotionFormatError(f"duplicate joint name {name!r}", path, ln)
        names.add(name)
        joints.append(_Joint(name=name, parent=parent, line=ln, end_site=end_site))
        tk.expect("{")
        return len(joints) - 1

    stack = [open_joint(-1, ln, False)]
    while stack:
        cur = joints[stack[-1]]
        tok, ln = tk.next("OFFSET, CHANNELS, JOINT, End Site or '}'")
        word = tok.upper()
        if word == "OFFSET":
            if cur.offset is not None:
                raise MotionFormatError(f"joint {cur.name!r} has two OFFSETs", path, ln)
            cur.offset = [tk.number(f"OFFSET of {cur.name!r}") for _ in range(3)]
        elif word == "CHANNELS":
            if cur.end_site:
                raise MotionFormatError("End Site cannot have CHANNELS", path, ln)
            if cur.channels:
                raise MotionFormatError(f"joint {cur.name!r} has two CHANNELS lines", path, ln)
            n = tk.number(f"CHANNELS count of {cur.name!r}")
            if n != int(n) or not 0 <= n <= 6:
                raise MotionFormatError(f"CHANNELS count must be 0..6, got {n:g}", path, ln)
            seen = set()
            for _ in range(int(n)):
                c, cl = tk.next(f"channel name of {cur.name!r}")
                m = _CHANNEL_RE.match(c)
                if m is None:
                    raise MotionFormatError(
                        f"unknown channel {c!r} of joint {cur.name!r}", path, cl
                    )
                canon = m.group(1).upper() + m.group(2).lower()
                if canon in seen:
                    raise MotionFormatError(
                        f"channel {canon} repeated in joint {cur.name!r}", path, cl
                    )
                seen.add(canon)
                cur.channels.append(canon)
        elif word == "JOINT":
            if cur.end_site:
                raise MotionFormatError("End Site cannot have child joints", path, ln)
            stack.append(open_joint(stack[-1], ln, False))
        elif word == "END":
            if cur.end_site:
                raise MotionFormatError("End Site cannot have child joints", path, ln)
            tok2, ln2 = tk.next("'Site'")
            if tok2.upper() != "SITE":
                raise MotionFormatError(f"expected 'Site' after 'End', found {tok2!r}", path, ln2)
            stack.append(open_joint(stack[-1], ln, True))
        elif word == "}":
            if cur.offset is None:
                raise MotionFormatError(f"joint {cur.name!r} has no OFFSET", path, ln)
            stack.pop()
        else:
            raise MotionFormatError(f"unexpected token {tok!r} in joint {cur.name!r}", path, ln)
    if tk.peek() is not None:
        tok, ln = tk.peek()
        raise MotionFormatError(
            f"unexpected {tok!r} after the root joint's block (one ROOT per file is supported)",
            path,
            ln,
        )
    return joints


#: largest magnitude (degrees) of a rotation channel: 1e5 degrees are 278 turns, more than any
#: unwrapped angle of a recorded motion; beyond it a value is corrupted (1e20 keeps no angle)
MAX_ANGLE_DEG = 1e5


def _parse_motion(lines: list[str], start: int, n_channels: int, path: str,
                  angles: list[str] | None = None):
    """Parse the lines after ``MOTION`` (``start`` = 0-based index of the first of them);
    ``angles``: per channel, its ``joint channel`` name when it is a rotation (else None)."""
    body = [(i + 1, s.strip()) for i, s in enumerate(lines[start:], start=start) if s.strip()]
    if len(body) < 2:
        raise MotionFormatError(
            "MOTION section lacks 'Frames:' and 'Frame Time:'", path, len(lines)
        )
    (ln_f, s_f), (ln_t, s_t) = body[0], body[1]
    m = _FRAMES_RE.match(s_f)
    if m is None:
        raise MotionFormatError(f"expected 'Frames: N', found {s_f[:40]!r}", path, ln_f)
    try:
        n_frames = int(m.group(1))
    except ValueError:
        raise MotionFormatError(
            f"frame count {m.group(1)!r} is not an integer", path, ln_f
        ) from None
    if n_frames < 1:
        raise MotionFormatError(f"frame count must be >= 1, got {n_frames}", path, ln_f)
    m = _FRAME_TIME_RE.match(s_t)
    if m is None:
        raise MotionFormatError(f"expected 'Frame Time: dt', found {s_t[:40]!r}", path, ln_t)
    try:
        dt = float(m.group(1))
    except ValueError:
        raise MotionFormatError(f"frame time {m.group(1)!r} is not a number", path, ln_t) from None
    if not (math.isfinite(dt) and dt > 0 and math.isfinite(1.0 / dt)):
        raise MotionFormatError(f"frame time must be positive, got {m.group(1)}", path, ln_t)
    if not MIN_FRAME_TIME <= dt <= MAX_FRAME_TIME:
        raise MotionFormatError(
            f"frame time {m.group(1)} s is not a plausible frame time: expected "
            f"{MIN_FRAME_TIME:g} to {MAX_FRAME_TIME:g} s ({1 / MAX_FRAME_TIME:g} to "
            f"{1 / MIN_FRAME_TIME:g} frames per second)", path, ln_t)
    data = body[2:]
    if len(data) < n_frames:
        last = data[-1][0] if data else ln_t
        raise MotionFormatError(
            f"truncated: header declares {n_frames} frames, found {len(data)}", path, last
        )
    if len(data) > n_frames:
        raise MotionFormatError(
            f"header declares {n_frames} frames but more data lines follow", path, data[n_frames][0]
        )
    rows: list[list[float]] = []
    for ln, s in data:
        parts = s.split()
        if len(parts) != n_channels:
            raise MotionFormatError(
                f"frame has {len(parts)} values, expected {n_channels} (one per channel)", path, ln
            )
        try:
            rows.append([float(t) for t in parts])
        except ValueError:
            bad_tok = next(t for t in parts if not _is_float(t))
            raise MotionFormatError(f"value {bad_tok!r} is not a number", path, ln) from None
    values = np.array(rows, dtype=np.float64).reshape(n_frames, n_channels)
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise MotionFormatError("frame holds NaN or infinity", path, data[k][0])
    if angles is not None:
        cols = [i for i, a in enumerate(angles) if a is not None]
        if cols:
            big = np.abs(values[:, cols]) > MAX_ANGLE_DEG
            if big.any():
                k, i = (int(x) for x in np.argwhere(big)[0])
                raise MotionFormatError(
                    f"frame {k}: {angles[cols[i]]} = {values[k, cols[i]]:g} degrees is not an "
                    f"angle (rotation channels are at most {MAX_ANGLE_DEG:g} degrees in "
                    f"magnitude; a corrupted value?)", path, data[k][0])
    return values, _snap_fps(m.group(1), dt)


def _is_float(t: str) -> bool:
    try:
        float(t)
    except ValueError:
        return False
    return True


def _snap_fps(text: str, dt: float) -> float:
    """Frames per second; an integer rate when it is consistent with the printed precision of
    the frame time (``.0083333`` -> 120, ``0.016667`` -> 60, but ``0.033367`` stays 29.97)."""
    frac = text.split(".")[-1] if "." in text and "e" not in text.lower() else ""
    half = 0.5 * 10.0 ** (-len(frac)) if frac else 0.0
    fps = 1.0 / dt
    k = round(fps)
    if k > 0 and half > 0 and abs(1.0 / k - dt) <= half:
        return float(k)
    return fps


def parse_bvh(text: str, path: str = "<bvh>") -> tuple[list[_Joint], np.ndarray, float]:
    """Parse BVH text into joints, the ``(T, C)`` channel values and the frame rate (fps)."""
    lines = text.splitlines()
    motion = next((i for i, s in enumerate(lines) if s.strip().upper() == "MOTION"), None)
    joints = _parse_hierarchy(lines if motion is None else lines[:motion], path)
    if motion is None:
        raise MotionFormatError("missing MOTION section", path, len(lines))
    n_channels = sum(len(j.channels) for j in joints)
    if n_channels == 0:
        raise MotionFormatError("the hierarchy has no channels", path, motion + 1)
    angles = [f"joint {j.name} channel {c}" if c.lower().endswith("rotation") else None
              for j in joints for c in j.channels]
    values, fps = _parse_motion(lines, motion + 1, n_channels, path, angles)
    return joints, values, fps


def _resolve_unit(
    names: list[str], path: str, unit: float | None, skeleton_map
) -> tuple[float, str | None]:
    from torchmocap.io.skeleton_maps import detect_family, load_skeleton_map

    if skeleton_map is not None:
        smap = load_skeleton_map(skeleton_map)
        family = smap.family
    else:
        family = detect_family(names, source_format="bvh", path=path)
        smap = load_skeleton_map(family) if family is not None else None
    if unit is None:
        if smap is None or smap.unit is None:
            return None, family  # inferred from the skeleton's size by the caller
        unit = smap.unit
    if isinstance(unit, bool) or not isinstance(unit, (int, float)) or not (
            math.isfinite(unit) and unit > 0):
        raise ValueError(f"unit: expected a positive number of metres per file unit, got {unit!r}")
    return float(unit), family


def _infer_unit(joints: list[_Joint], path: str, skeleton_map) -> float:
    """Metres per unit of a file no map gives a unit for, from its rest skeleton's size
    (:func:`~torchmocap.io.units.infer_length_unit`); metres when nothing fits, with a warning."""
    from torchmocap.io.units import infer_length_unit

    rest = MotionClip(
        joint_names=[j.name for j in joints], parents=[j.parent for j in joints],
        offsets=y_up_to_z_up(torch.tensor([j.offset for j in joints], dtype=torch.float64)),
        rotations=torch.eye(3, dtype=torch.float64).repeat(1, len(joints), 1, 1),
        root_translation=torch.zeros(1, 3, dtype=torch.float64), fps=1.0,
        axes=[torch.zeros(0, 3, dtype=torch.float64) for _ in joints], source_path=path)
    guess = infer_length_unit(rest, skeleton_map)
    if guess.unit is None:
        warnings.warn(f"{path}: unknown length unit (no skeleton map with a 'unit' matches, and "
                      f"{guess.describe()}); assuming metres - pass unit= (data.clip.unit: metres "
                      "per file unit)", stacklevel=3)
        return 1.0
    warnings.warn(f"{path}: no skeleton map gives the length unit; inferred "
                  f"{guess.describe()} - pass unit= (data.clip.unit) if that is wrong",
                  stacklevel=3)
    return guess.unit


def read_bvh(
    path: str | Path,
    unit: float | None = None,
    skip_frames: int = 0,
    skeleton_map: str | Path | None = None,
    dtype: torch.dtype = torch.float64,
) -> MotionClip:
    """Read a BVH file into a Z-up, metre :class:`MotionClip`.

    Args:
        path: the ``.bvh`` file.
        unit: metres per file length unit (e.g. 0.01 for cm). ``None``: the matched skeleton
            map's ``unit``; when no map gives one, inferred from the rest skeleton's size
            (:func:`~torchmocap.io.units.infer_length_unit`: m, cm, mm, inch or the CMU ASF
            unit, whichever makes it an adult's; metres when none does), with a warning.
        skip_frames: drop this many leading frames (e.g. 1 for the synthetic T-pose frame 0 of
            the cgspeed CMU MotionBuilder files). Nothing is dropped unless asked.
        skeleton_map: family name or YAML path to use instead of auto-detection.
        dtype: floating dtype of the clip's tensors.

    Raises:
        MotionFormatError: malformed file (message names file and line).
    """
    from torchmocap.inputs import note_input

    path = str(path)
    note_input(path)
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise MotionFormatError(f"cannot read file ({e.strerror or e})", path) from None
    try:
        text = raw.decode("utf-8-sig")  # a byte-order mark (some Windows editors) is dropped
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    joints, values, fps = parse_bvh(text, path)
    if not 0 <= skip_frames < values.shape[0]:
        raise ValueError(f"skip_frames={skip_frames} leaves no frames of {values.shape[0]}")
    values = values[skip_frames:]
    names = [j.name for j in joints]
    unit, family = _resolve_unit(names, path, unit, skeleton_map)
    if unit is None:
        unit = _infer_unit(joints, path, skeleton_map)

    T = values.shape[0]
    vals = torch.from_numpy(values).to(torch.float64)
    offsets = y_up_to_z_up(torch.tensor([j.offset for j in joints], dtype=torch.float64) * unit)
    rotations = torch.eye(3, dtype=torch.float64).repeat(T, len(joints), 1, 1)
    root_translation = torch.zeros(T, 3, dtype=torch.float64)
    local_translations: dict[str, torch.Tensor] = {}
    axes: list[torch.Tensor] = []
    col = 0
    for j, jt in enumerate(joints):
        rot_cols, rot_axes, pos = [], [], {}
        for c in jt.channels:
            if c.endswith("rotation"):
                rot_cols.append(col)
                rot_axes.append(_zup_axis(c[0].lower()))
            else:
                pos[_AXIS_INDEX[c[0].lower()]] = col
            col += 1
        ax = torch.stack(rot_axes) if rot_axes else torch.zeros(0, 3, dtype=torch.float64)
        axes.append(ax)
        if rot_cols:
            rotations[:, j] = angles_to_matrix(torch.deg2rad(vals[:, rot_cols]), ax)
        if pos:
            base = (
                torch.zeros(3, dtype=torch.float64)
                if j == 0
                else torch.tensor(jt.offset, dtype=torch.float64)
            )
            tr = base.repeat(T, 1)
            for k, c in pos.items():
                tr[:, k] = vals[:, c]
            tr = y_up_to_z_up(tr * unit)
            if j == 0:
                root_translation = tr
            else:
                local_translations[jt.name] = tr
    try:
        clip = MotionClip(
            joint_names=names,
            parents=[jt.parent for jt in joints],
            offsets=offsets,
            rotations=rotations,
            root_translation=root_translation,
            fps=fps,
            axes=axes,
            local_translations=local_translations,
            source_format="bvh",
            skeleton_family=family,
            source_path=path,
            unit=unit,
            channels=[tuple(jt.channels) for jt in joints],
        )
    except ValueError as e:
        raise MotionFormatError(str(e), path) from None
    return clip.to(dtype) if dtype != torch.float64 else clip


# ---------------------------------------------------------------------------------- writer
_DEFAULT_ROT = ("Zrotation", "Yrotation", "Xrotation")


def _channels_for(clip: MotionClip, j: int) -> tuple[str, ...]:
    """Channels to write for joint ``j``: the file's own when they still fit, else Z-Y-X."""
    name = clip.joint_names[j]
    has_pos = j == 0 or name in clip.local_translations
    if clip.channels is not None:
        ch = tuple(clip.channels[j])
        rot = [c for c in ch if c.endswith("rotation")]
        pos = [c for c in ch if c.endswith("position")]
        if len(rot) == clip.axes[j].shape[0]:
            ax = torch.stack([_zup_axis(c[0].lower()) for c in rot]) if rot else None
            same = ax is None or torch.allclose(ax, clip.axes[j].to(torch.float64), atol=1e-9)
            if same and (len(pos) == 3 or (not pos and not has_pos)):
                return ch
    rot = _DEFAULT_ROT
    return (("Xposition", "Yposition", "Zposition") + rot) if has_pos else rot


def _fmt(v: float, precision: int) -> str:
    s = f"{v:.{precision}f}"
    if "." in s:
        s = s.rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def write_bvh(
    path: str | Path, clip: MotionClip, unit: float | None = None, precision: int = 8
) -> Path:
    """Write ``clip`` as a BVH file (Y-up), atomically: a temp file in the same folder is
    renamed over ``path`` only when complete, so no half-written file is ever left.

    Args:
        path: output ``.bvh``.
        clip: any :class:`MotionClip` (also :meth:`MotionClip.from_skeleton` of a human31 track).
        unit: metres per written length unit. ``None``: the clip's skeleton map unit when it
            has one (so that reading the file back detects the same unit), else metres.
        precision: decimals of the written numbers (degrees and length units).

    Channels: a clip read from BVH keeps each joint's channel order; other joints get
    ``Zrotation Yrotation Xrotation`` (exact for any local rotation), every non-leaf joint gets
    rotation channels (zeros where it has no DoF) so common tools read the file, and a leaf
    named other than ``<parent>_end`` is written as a JOINT with a zero End Site so its name
    survives. Joint positions after reading back equal the clip's to ~10^-precision units.
    """
    from torchmocap.io.skeleton_maps import known_families, load_skeleton_map

    path = Path(path)
    clip = clip.to(device="cpu")
    if unit is None:
        unit = 1.0
        if clip.skeleton_family in known_families():
            u = load_skeleton_map(clip.skeleton_family).unit
            unit = u if u is not None else 1.0
    if not (math.isfinite(unit) and unit > 0):
        raise ValueError(f"unit: expected a positive number of metres per unit, got {unit!r}")
    dt = torch.float64
    J, T = clip.num_joints, clip.num_frames
    kids = [clip.children(j) for j in range(J)]
    is_end = [
        j > 0
        and not kids[j]
        and clip.axes[j].shape[0] == 0
        and clip.joint_names[j] not in clip.local_translations
        and clip.joint_names[j].startswith(f"{clip.joint_names[clip.parents[j]]}_end")
        for j in range(J)
    ]
    chans: list[tuple[str, ...]] = [() if is_end[j] else _channels_for(clip, j) for j in range(J)]
    off = z_up_to_y_up(clip.offsets.to(dt)) / unit

    def vec(v) -> str:
        return " ".join(_fmt(float(x), precision) for x in v)

    out: list[str] = ["HIERARCHY"]
    order: list[int] = []

    def emit(j: int, depth: int) -> None:
        ind = "\t" * depth
        if is_end[j]:
            out.extend([f"{ind}End Site", f"{ind}{{", f"{ind}\tOFFSET {vec(off[j])}", f"{ind}}}"])
            return
        out.append(f"{ind}{'ROOT' if j == 0 else 'JOINT'} {clip.joint_names[j]}")
        out.append(f"{ind}{{")
        out.append(f"{ind}\tOFFSET {vec(off[j])}")
        out.append(f"{ind}\tCHANNELS {len(chans[j])}" + "".join(" " + c for c in chans[j]))
        order.append(j)
        for c in kids[j]:
            emit(c, depth + 1)
        if not kids[j]:
            out.extend([f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET 0 0 0", f"{ind}\t}}"])
        out.append(f"{ind}}}")

    emit(0, 0)
    cols: list[torch.Tensor] = []
    for j in order:
        rot = [c for c in chans[j] if c.endswith("rotation")]
        if rot:
            ax = torch.stack([_zup_axis(c[0].lower()) for c in rot])
            ang = torch.rad2deg(matrix_to_angles(clip.rotations[:, j].to(dt), ax))
        pos_src = None
        if any(c.endswith("position") for c in chans[j]):
            name = clip.joint_names[j]
            tr = (
                clip.root_translation
                if j == 0
                else clip.local_translations.get(name, clip.offsets[j].expand(T, 3))
            )
            pos_src = z_up_to_y_up(tr.to(dt)) / unit
        k = 0
        for c in chans[j]:
            if c.endswith("rotation"):
                cols.append(ang[:, k])
                k += 1
            else:
                cols.append(pos_src[:, _AXIS_INDEX[c[0].lower()]])
    values = torch.stack(cols, -1).numpy() if cols else np.zeros((T, 0))
    out.extend(["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / clip.fps:.10g}"])
    for row in values.tolist():
        out.append(" ".join(_fmt(v, precision) for v in row))
    text = "\n".join(out) + "\n"
    write_text_atomic(path, text)
    return path


