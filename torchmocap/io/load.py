"""``load_motion``: open any supported motion file by its extension."""

from __future__ import annotations

import math
from pathlib import Path

from torchmocap.io.errors import MotionFormatError
from torchmocap.io.motion import MotionClip

__all__ = ["MOTION_SUFFIXES", "bundled_clip_path", "find_asf", "load_motion"]

#: File extensions :func:`load_motion` understands.
MOTION_SUFFIXES = (".bvh", ".amc", ".asf")


def find_asf(amc_path: str | Path) -> Path:
    """The ASF of an AMC file, from the AMC's folder: the only ``.asf`` there, or else the one
    whose name is the AMC's name up to an underscore (the CMU and HDM05 conventions:
    ``01_01.amc`` -> ``01.asf``, ``HDM_bk_hop..._120.amc`` -> ``HDM_bk.asf``; the longest such
    name when several match, compared case-insensitively).

    Raises:
        MotionFormatError: no ``.asf`` file there, or several and none (or no single longest)
            named after the AMC (then pass ``asf=``).
    """
    from torchmocap.inputs import note_input

    amc_path = Path(amc_path)
    note_input(amc_path.parent)  # which .asf files are there decides the choice
    found = sorted(p for p in amc_path.parent.glob("*") if p.suffix.lower() == ".asf")
    if len(found) == 1:
        return found[0]
    stem = amc_path.stem.lower()
    named = [p for p in found if stem == p.stem.lower() or stem.startswith(p.stem.lower() + "_")]
    longest = max((len(p.stem) for p in named), default=0)
    named = [p for p in named if len(p.stem) == longest]
    if len(named) == 1:
        return named[0]
    what = "no .asf file" if not found else f"{len(found)} .asf files"
    detail = "" if not found else (
        f" and {'none' if not named else len(named)} named after it "
        f"({', '.join(p.name for p in found)})")
    raise MotionFormatError(
        f"{what} beside this AMC{detail}; name its skeleton explicitly (asf=... / --asf)",
        amc_path)


def load_motion(
    path: str | Path,
    asf: str | Path | None = None,
    unit: float | None = None,
    skip_frames: int | str = 0,
    fps: float | None = None,
    skeleton_map: str | Path | None = None,
    up: str = "auto",
) -> MotionClip:
    """Read a ``.bvh``, an ``.amc`` (with ``asf`` or the ``.asf`` :func:`find_asf` picks), or an
    ``.asf`` alone (its rest pose as a one-frame clip) into a Z-up metre :class:`MotionClip`.

    Args:
        path: the motion file.
        asf: the skeleton of an AMC file.
        unit: metres per file length unit (default: from the file or its skeleton map).
        skip_frames: leading frames to drop (e.g. 1 for the cgspeed CMU MotionBuilder T-pose),
            or ``"auto"``: the leading frames that are a reference pose rather than motion
            (:func:`~torchmocap.io.trim.leading_reference_frames`), with a warning.
        fps: frame rate of an AMC (``None``: 120, the CMU and HDM05 rate); ignored for BVH
            (the file states it). Must be positive and finite when given (``fps=0`` is an
            error, not the default).
        skeleton_map: family name or map YAML (default: auto-detected); for BVH it also
            supplies the length unit.
        up: the file's up axis: ``"auto"`` (the default: a clip whose rest pose does not stand
            along +z after the usual Y-up reading is turned upright, with a warning — see
            :func:`~torchmocap.io.upright.upright`), ``"y"`` (as read) or ``"z"`` (a Z-up
            file).
    """
    from torchmocap.io.upright import UP_AXES

    if up not in UP_AXES:
        raise ValueError(f"up: expected one of {UP_AXES}, got {up!r}")
    auto_skip = skip_frames == "auto"
    if not auto_skip and (isinstance(skip_frames, bool) or not isinstance(skip_frames, int)):
        raise ValueError(f"skip_frames: expected a number of frames >= 0 or 'auto', got "
                         f"{skip_frames!r}")
    clip = _read(path, asf, unit, 0 if auto_skip else skip_frames, fps, skeleton_map)
    if auto_skip:
        from torchmocap.io.trim import trim_reference_frames

        clip, _ = trim_reference_frames(clip, path)
    if clip.num_joints < 2:
        return clip
    from torchmocap.io.upright import upright

    clip, note = upright(clip, up, skeleton_map)
    if note is not None:
        import warnings

        warnings.warn(f"{path}: {note}", stacklevel=2)
    return clip


def _read(path, asf, unit, skip_frames, fps, skeleton_map) -> MotionClip:
    from torchmocap.io.asf import read_amc, read_asf
    from torchmocap.io.bvh import read_bvh

    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float))
                            or not math.isfinite(fps) or fps <= 0):
        raise ValueError(f"fps: expected a positive finite frame rate or None, got {fps!r}")
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".bvh":
        return read_bvh(path, unit=unit, skip_frames=skip_frames, skeleton_map=skeleton_map)
    if suffix == ".amc":
        asf_path = Path(asf) if asf is not None else find_asf(path)
        return read_amc(
            path,
            asf_path,
            fps=120.0 if fps is None else float(fps),
            skip_frames=skip_frames,
            unit=unit,
            skeleton_map=skeleton_map,
        )
    if suffix == ".asf":
        clip = read_asf(path).rest_clip(unit)
        if skeleton_map is not None:
            from torchmocap.io.skeleton_maps import load_skeleton_map

            clip.skeleton_family = load_skeleton_map(skeleton_map).family
        return clip
    raise MotionFormatError(
        f"unsupported motion file type {suffix or '(none)'!r}; expected one of {MOTION_SUFFIXES}",
        path,
    )


def bundled_clip_path(name: str = "cmu_131_01_walk") -> Path:
    """Path of a motion clip shipped in ``torchmocap/assets/clips`` (CMU licence beside it).

    ``cmu_131_01_walk``: 4 s (480 frames, 120 fps) of CMU subject 131's stylised walk, BVH.
    """
    from importlib import resources

    res = resources.files("torchmocap") / "assets" / "clips" / f"{name}.bvh"
    if not res.is_file():
        raise FileNotFoundError(f"no bundled clip {name!r} in torchmocap/assets/clips")
    return Path(str(res))
