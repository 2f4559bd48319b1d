"""Acclaim ASF (skeleton) / AMC (motion) reader, CMU and HDM05 conventions.

ASF: ``:units`` ``length L`` means one file unit is ``1/L`` inch (CMU and HDM05: ``L = 0.45``,
0.0564444 m); ``angle deg|rad``. Each bone has a rest ``direction`` (unit vector, global frame),
a ``length``, an ``axis ax ay az ORDER`` pre-rotation ``C`` (applied in ORDER, so ``XYZ`` gives
``C = Rz(az) Ry(ay) Rx(ax)``) and a ``dof`` list. An AMC line ``bone v1 v2 ...`` gives the
angles of its dofs, applied in the listed order: ``M = R_dk(vk) ... R_d1(v1)``, and the bone's
local rotation is ``C M C^-1`` = rotations about ``C``'s columns ``C e_dk, ..., C e_d1``. The
root's ``order`` names the AMC root columns (``TX TY TZ RX RY RZ``) and its ``axis`` the rotation
order (``XYZ``: ``Rz Ry Rx``); a non-zero root ``orientation`` ``O`` is applied as ``O M O^-1``.
AMC values are in the unit of the AMC's ``:DEGREES`` / ``:RADIANS`` header, else the ASF's.

Joints of the resulting :class:`MotionClip`: ``root``, then one joint per bone at the bone's
*start* (``lfemur`` = hip, ``ltibia`` = knee, ``lfoot`` = ankle) whose offset is the parent
bone's vector, and a 0-DoF leaf ``<bone>_end`` at the tip of every bone without children.
Files are decoded as Latin-1 (HDM05 AMC headers hold a non-UTF-8 byte); CRLF is fine.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchmocap.io._euler import angles_to_matrix
from torchmocap.io.errors import MotionFormatError
from torchmocap.io.motion import MotionClip, y_up_to_z_up

__all__ = ["AsfBone", "AsfSkeleton", "parse_asf", "read_amc", "read_asf", "read_asf_amc"]

_INCH = 0.0254
_ROT_DOFS = ("rx", "ry", "rz")
_ROOT_CHANNELS = ("TX", "TY", "TZ", "RX", "RY", "RZ")


@dataclass
class AsfBone:
    """One ``:bonedata`` block (lengths in file units, angles in degrees or radians as the file)."""

    name: str
    direction: tuple[float, float, float]
    length: float
    axis: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis_order: str = "XYZ"
    dof: tuple[str, ...] = ()
    line: int = 0


@dataclass
class AsfSkeleton:
    """A parsed ASF file."""

    path: str
    unit: float  # metres per file length unit
    angle: str  # "deg" or "rad"
    root_order: tuple[str, ...]
    root_axis: str
    root_position: tuple[float, float, float]
    root_orientation: tuple[float, float, float]
    bones: dict[str, AsfBone]
    children: dict[str, list[str]] = field(default_factory=dict)

    def joint_order(self) -> list[tuple[str, str | None, bool]]:
        """``(joint name, parent joint name, is end site)`` in depth-first order from the root."""
        out: list[tuple[str, str | None, bool]] = [("root", None, False)]
        stack = [(c, "root") for c in reversed(self.children.get("root", []))]
        while stack:
            b, p = stack.pop()
            out.append((b, p, False))
            kids = self.children.get(b, [])
            if not kids:
                out.append((f"{b}_end", b, True))
            stack.extend((c, b) for c in reversed(kids))
        return out

    def rest_clip(self, unit: float | None = None) -> MotionClip:
        """One-frame clip of the rest pose (all dofs zero)."""
        zeros = {b: np.zeros((1, len(bone.dof))) for b, bone in self.bones.items()}
        return _build_clip(
            self, np.zeros((1, len(self.root_order))), zeros, 120.0, unit or self.unit, None
        )


def _err(msg: str, path: str, line: int | None = None) -> MotionFormatError:
    return MotionFormatError(msg, path, line)


def _floats(tokens: list[str], n: int, what: str, path: str, ln: int) -> list[float]:
    if len(tokens) != n:
        raise _err(f"{what}: expected {n} numbers, found {len(tokens)}", path, ln)
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        raise _err(f"{what}: not a number in {' '.join(tokens)!r}", path, ln) from None
    if not all(math.isfinite(v) for v in vals):
        raise _err(f"{what}: not finite", path, ln)
    return vals


def _check_order(order: str, path: str, ln: int) -> str:
    o = order.upper()
    if len(o) != 3 or sorted(o) != ["X", "Y", "Z"]:
        raise _err(f"rotation order must be a permutation of XYZ, got {order!r}", path, ln)
    return o


def parse_asf(text: str, path: str = "<asf>") -> AsfSkeleton:
    """Parse ASF text. Raises :class:`MotionFormatError` naming the line on any defect."""
    lines = text.splitlines()
    section = None
    length_unit: float | None = None
    angle = "deg"
    root: dict[str, object] = {}
    bones: dict[str, AsfBone] = {}
    cur: dict[str, object] | None = None
    children: dict[str, list[str]] = {}
    has_parent: set[str] = set()
    in_hier = False
    seen_sections: set[str] = set()

    def close_bone(ln: int) -> None:
        nonlocal cur
        assert cur is not None
        for key in ("name", "direction", "length"):
            if key not in cur:
                raise _err(f"bone block ending here has no '{key}'", path, ln)
        d = np.array(cur["direction"], dtype=float)
        n = float(np.linalg.norm(d))
        length = float(cur["length"])
        if length < 0:
            raise _err(f"bone {cur['name']!r}: negative length", path, int(cur["line"]))
        if n < 1e-12:
            raise _err(f"bone {cur['name']!r}: zero direction", path, int(cur["line"]))
        name = str(cur["name"])
        if name in bones or name == "root":
            raise _err(f"duplicate bone name {name!r}", path, int(cur["line"]))
        bones[name] = AsfBone(
            name=name,
            direction=tuple(d / n),
            length=length,
            axis=tuple(cur.get("axis", (0.0, 0.0, 0.0))),
            axis_order=str(cur.get("order", "XYZ")),
            dof=tuple(cur.get("dof", ())),
            line=int(cur["line"]),
        )
        cur = None

    for ln, raw in enumerate(lines, start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        toks = s.split()
        if s.startswith(":"):
            if cur is not None:
                raise _err(f"section {toks[0]} starts inside an unfinished bone block", path, ln)
            if in_hier:
                raise _err(f"section {toks[0]} starts inside the unfinished :hierarchy", path, ln)
            section = toks[0].lower()
            seen_sections.add(section)
            continue
        key = toks[0].lower()
        if section == ":units":
            if key == "length":
                length_unit = _floats(toks[1:], 1, "units length", path, ln)[0]
                if length_unit <= 0:
                    raise _err("units length must be positive", path, ln)
            elif key == "angle":
                if len(toks) != 2 or toks[1].lower() not in ("deg", "rad"):
                    raise _err(f"units angle must be deg or rad, got {s!r}", path, ln)
                angle = toks[1].lower()
        elif section == ":root":
            if key == "order":
                order = tuple(t.upper() for t in toks[1:])
                if (
                    not order
                    or any(t not in _ROOT_CHANNELS for t in order)
                    or len(set(order)) != len(order)
                ):
                    raise _err(
                        f"root order must list channels of {_ROOT_CHANNELS} once each", path, ln
                    )
                root["order"] = order
            elif key == "axis":
                if len(toks) != 2:
                    raise _err("root axis must be one rotation order such as XYZ", path, ln)
                root["axis"] = _check_order(toks[1], path, ln)
            elif key in ("position", "orientation"):
                root[key] = tuple(_floats(toks[1:], 3, f"root {key}", path, ln))
            else:
                raise _err(f"unknown root field {toks[0]!r}", path, ln)
        elif section == ":bonedata":
            if key == "begin":
                if cur is not None:
                    raise _err("'begin' inside an unfinished bone block", path, ln)
                cur = {"line": ln}
            elif key == "end":
                if cur is None:
                    raise _err("'end' without 'begin'", path, ln)
                close_bone(ln)
            elif cur is None:
                raise _err(f"{toks[0]!r} outside a begin/end bone block", path, ln)
            elif key == "name":
                if len(toks) != 2:
                    raise _err("bone name must be one word", path, ln)
                cur["name"] = toks[1]
            elif key == "direction":
                cur["direction"] = _floats(toks[1:], 3, "direction", path, ln)
            elif key == "length":
                cur["length"] = _floats(toks[1:], 1, "length", path, ln)[0]
            elif key == "axis":
                if len(toks) != 5:
                    raise _err("axis needs three angles and an order (e.g. 0 0 20 XYZ)", path, ln)
                cur["axis"] = tuple(_floats(toks[1:4], 3, "axis", path, ln))
                cur["order"] = _check_order(toks[4], path, ln)
            elif key == "dof":
                dof = tuple(t.lower() for t in toks[1:])
                for d in dof:
                    if d not in _ROT_DOFS:
                        raise _err(f"unsupported dof {d!r} (rx, ry, rz are supported)", path, ln)
                if len(set(dof)) != len(dof) or not dof:
                    raise _err(
                        f"dof list {' '.join(toks[1:])!r} is empty or repeats an axis", path, ln
                    )
                cur["dof"] = dof
            elif key in ("id", "limits", "bodymass", "cofmass") or s.startswith("("):
                continue
            else:
                raise _err(f"unknown bone field {toks[0]!r}", path, ln)
        elif section == ":hierarchy":
            if key == "begin":
                in_hier = True
            elif key == "end":
                in_hier = False
            elif not in_hier:
                raise _err(f"{toks[0]!r} outside begin/end of :hierarchy", path, ln)
            else:
                parent = toks[0]
                if parent != "root" and parent not in bones:
                    raise _err(f"hierarchy names unknown bone {parent!r}", path, ln)
                for c in toks[1:]:
                    if c not in bones:
                        raise _err(f"hierarchy names unknown bone {c!r}", path, ln)
                    if c in has_parent:
                        raise _err(f"bone {c!r} has two parents", path, ln)
                    has_parent.add(c)
                    children.setdefault(parent, []).append(c)
        # other sections (:version, :name, :documentation, unknown) are ignored
    if cur is not None:
        raise _err("file ends inside a bone block", path, len(lines))
    if in_hier:
        raise _err("file ends inside the :hierarchy block", path, len(lines))
    for sec in (":root", ":bonedata", ":hierarchy"):
        if sec not in seen_sections:
            raise _err(f"missing {sec} section", path, len(lines))
    if "order" not in root:
        raise _err("root has no 'order'", path, len(lines))
    # connectivity (cycles / unreachable bones)
    reached, stack = set(), ["root"]
    while stack:
        b = stack.pop()
        for c in children.get(b, []):
            if c in reached:
                raise _err(f"hierarchy has a cycle through {c!r}", path, bones[c].line)
            reached.add(c)
            stack.append(c)
    orphans = [b for b in bones if b not in reached]
    if orphans:
        raise _err(f"bones not connected to the root: {orphans}", path, bones[orphans[0]].line)
    if length_unit is None:
        warnings.warn(
            f"{path}: no ':units length'; assuming inches (Acclaim default)", stacklevel=3
        )
        length_unit = 1.0
    return AsfSkeleton(
        path=path,
        unit=_INCH / length_unit,
        angle=angle,
        root_order=tuple(root["order"]),
        root_axis=str(root.get("axis", "XYZ")),
        root_position=tuple(root.get("position", (0.0, 0.0, 0.0))),
        root_orientation=tuple(root.get("orientation", (0.0, 0.0, 0.0))),
        bones=bones,
        children=children,
    )


def _read_text(path: str) -> str:
    from torchmocap.inputs import note_input

    note_input(path)
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise MotionFormatError(f"cannot read file ({e.strerror or e})", path) from None
    return raw.removeprefix(b"\xef\xbb\xbf").decode("latin-1")  # a UTF-8 byte-order mark


def read_asf(path: str | Path) -> AsfSkeleton:
    """Read and parse an ASF file (Latin-1)."""
    path = str(path)
    return parse_asf(_read_text(path), path)


def _unit_axes(order: str) -> torch.Tensor:
    return torch.eye(3, dtype=torch.float64)[["XYZ".index(c) for c in order]]


def _matrix_from_order(
    angles_deg: tuple[float, float, float], order: str, rad: bool
) -> torch.Tensor:
    """Rotation applying the ``order`` axes first to last: ``XYZ`` -> ``Rz Ry Rx``."""
    a = torch.tensor(angles_deg, dtype=torch.float64)
    a = a if rad else torch.deg2rad(a)
    idx = ["XYZ".index(c) for c in order]
    return angles_to_matrix(a[idx].flip(0), _unit_axes(order).flip(0))


def _build_clip(
    asf: AsfSkeleton,
    root_vals: np.ndarray,
    bone_vals: dict[str, np.ndarray],
    fps: float,
    unit: float,
    amc_path: str | None,
    values_rad: bool | None = None,
) -> MotionClip:
    rad = asf.angle == "rad"  # ASF axis / orientation angles
    vrad = rad if values_rad is None else values_rad  # AMC values (its :RADIANS / :DEGREES)
    T = root_vals.shape[0]
    order = asf.joint_order()
    names = [n for n, _, _ in order]
    index = {n: i for i, n in enumerate(names)}
    A = y_up_to_z_up(torch.eye(3, dtype=torch.float64)).T  # columns: Z-up images of x, y, z

    def bone_vec(b: str) -> torch.Tensor:
        bone = asf.bones[b]
        return y_up_to_z_up(torch.tensor(bone.direction, dtype=torch.float64) * bone.length * unit)

    offsets = torch.zeros(len(names), 3, dtype=torch.float64)
    parents, axes = [], []
    rotations = torch.eye(3, dtype=torch.float64).repeat(T, len(names), 1, 1)
    for j, (n, p, is_end) in enumerate(order):
        parents.append(-1 if p is None else index[p])
        if j == 0:
            offsets[0] = y_up_to_z_up(torch.tensor(asf.root_position, dtype=torch.float64) * unit)
            rot_cols = [c for c in asf.root_axis]  # applied first to last
            O = _matrix_from_order(asf.root_orientation, "XYZ", rad)
            ax_src = O @ _unit_axes("".join(rot_cols)).T  # columns
            ax = (A @ ax_src).T.flip(0)  # Z-up, matrix product order (last applied first)
            cols = [
                asf.root_order.index(f"R{c}") if f"R{c}" in asf.root_order else None
                for c in rot_cols
            ]
            ang = torch.stack(
                [
                    torch.from_numpy(root_vals[:, c])
                    if c is not None
                    else torch.zeros(T, dtype=torch.float64)
                    for c in cols
                ],
                -1,
            ).flip(-1)
            axes.append(ax)
            rotations[:, 0] = angles_to_matrix(ang if vrad else torch.deg2rad(ang), ax)
            continue
        if p != "root":
            offsets[j] = bone_vec(p)
        if is_end:
            offsets[j] = bone_vec(p)
            axes.append(torch.zeros(0, 3, dtype=torch.float64))
            continue
        bone = asf.bones[n]
        if not bone.dof:
            axes.append(torch.zeros(0, 3, dtype=torch.float64))
            continue
        C = _matrix_from_order(bone.axis, bone.axis_order, rad)
        cols_src = C @ torch.eye(3, dtype=torch.float64)[:, [_ROT_DOFS.index(d) for d in bone.dof]]
        ax = (A @ cols_src).T.flip(0)
        ang = torch.from_numpy(bone_vals[n]).flip(-1)
        axes.append(ax)
        rotations[:, j] = angles_to_matrix(ang if vrad else torch.deg2rad(ang), ax)
    trans = torch.zeros(T, 3, dtype=torch.float64)
    for k, c in enumerate("XYZ"):
        if f"T{c}" in asf.root_order:
            trans[:, k] = torch.from_numpy(root_vals[:, asf.root_order.index(f"T{c}")])
    root_translation = y_up_to_z_up(trans * unit)
    from torchmocap.io.skeleton_maps import detect_family

    family = detect_family(names, source_format="asf", path=asf.path)
    try:
        return MotionClip(
            joint_names=names,
            parents=parents,
            offsets=offsets,
            rotations=rotations,
            root_translation=root_translation,
            fps=float(fps),
            axes=axes,
            source_format="asf",
            skeleton_family=family,
            source_path=amc_path or asf.path,
            unit=unit,
        )
    except ValueError as e:
        raise MotionFormatError(str(e), amc_path or asf.path) from None


def _parse_amc(text: str, asf: AsfSkeleton, path: str):
    lines = text.splitlines()
    dof_bones = {b: len(bone.dof) for b, bone in asf.bones.items() if bone.dof}
    n_root = len(asf.root_order)
    frames: list[dict[str, list[float]]] = []
    frame_lines: list[int] = []
    prev_number: int | None = None
    values_rad: bool | None = None
    for ln, raw in enumerate(lines, start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        if s.startswith(":"):
            key = s.upper()
            if key in (":RADIANS", ":DEGREES"):
                values_rad = key == ":RADIANS"
            continue
        toks = s.split()
        if len(toks) == 1:
            try:
                number = int(toks[0])
            except ValueError:
                raise _err(f"expected a frame number, found {toks[0]!r}", path, ln) from None
            if prev_number is not None and number != prev_number + 1:
                raise _err(f"frame {number} follows frame {prev_number}", path, ln)
            prev_number = number
            frames.append({})
            frame_lines.append(ln)
            continue
        if not frames:
            raise _err(f"bone line {toks[0]!r} before the first frame number", path, ln)
        name = toks[0]
        if name == "root":
            want = n_root
        elif name in asf.bones:
            want = len(asf.bones[name].dof)
        else:
            raise _err(
                f"bone {name!r} is not in the ASF {asf.path} (mismatched ASF/AMC?)", path, ln
            )
        if name in frames[-1]:
            raise _err(f"bone {name!r} appears twice in frame {prev_number}", path, ln)
        frames[-1][name] = _floats(toks[1:], want, f"bone {name!r} (ASF dof count)", path, ln)
    if not frames:
        raise _err("no frames", path, len(lines))
    needed = ["root", *dof_bones]
    for fi, fr in enumerate(frames):
        missing = [b for b in needed if b not in fr]
        if missing:
            raise _err(
                f"frame starting here lacks bones {missing[:5]}"
                + (" (truncated file?)" if fi == len(frames) - 1 else ""),
                path,
                frame_lines[fi],
            )
    root_vals = np.array([fr["root"] for fr in frames], dtype=np.float64).reshape(
        len(frames), n_root
    )
    bone_vals = {
        b: np.array([fr[b] for fr in frames], dtype=np.float64).reshape(len(frames), k)
        for b, k in dof_bones.items()
    }
    return root_vals, bone_vals, values_rad


def read_amc(
    path: str | Path,
    asf: AsfSkeleton | str | Path,
    fps: float = 120.0,
    skip_frames: int = 0,
    unit: float | None = None,
    skeleton_map: str | Path | None = None,
    dtype: torch.dtype = torch.float64,
) -> MotionClip:
    """Read an AMC motion with its ASF skeleton into a Z-up, metre :class:`MotionClip`.

    Args:
        path: the ``.amc`` file.
        asf: its skeleton (an :class:`AsfSkeleton` or the ``.asf`` path).
        fps: frame rate (AMC files do not store it; CMU and HDM05 record at 120).
        skip_frames: drop this many leading frames.
        unit: metres per length unit, overriding the ASF ``:units`` (rarely needed).
        skeleton_map: family name or map YAML to label the clip with instead of detection.

    Raises:
        MotionFormatError: malformed AMC, or an AMC that does not match the ASF (unknown bone,
            wrong number of values), naming the file and line.
    """
    path = str(path)
    if not isinstance(asf, AsfSkeleton):
        asf = read_asf(asf)
    if isinstance(fps, bool) or not (isinstance(fps, (int, float)) and math.isfinite(fps)
                                     and fps > 0):
        raise ValueError(f"fps: expected a positive finite frame rate, got {fps!r}")
    root_vals, bone_vals, values_rad = _parse_amc(_read_text(path), asf, path)
    T = root_vals.shape[0]
    if not 0 <= skip_frames < T:
        raise ValueError(f"skip_frames={skip_frames} leaves no frames of {T}")
    root_vals = root_vals[skip_frames:]
    bone_vals = {b: v[skip_frames:] for b, v in bone_vals.items()}
    clip = _build_clip(
        asf, root_vals, bone_vals, fps, float(unit or asf.unit), path, values_rad=values_rad
    )
    if skeleton_map is not None:
        from torchmocap.io.skeleton_maps import load_skeleton_map

        clip.skeleton_family = load_skeleton_map(skeleton_map).family
    return clip.to(dtype) if dtype != torch.float64 else clip


def read_asf_amc(asf_path: str | Path, amc_path: str | Path, **kwargs) -> MotionClip:
    """``read_amc(amc_path, asf_path, **kwargs)`` with the arguments in file-pair order."""
    return read_amc(amc_path, asf_path, **kwargs)
