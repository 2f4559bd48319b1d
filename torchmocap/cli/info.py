"""``torchmocap-info PATH [--asf ASF] [--skeleton-map NAME|YAML]``: describe a motion or
camera-calibration file as JSON.

Motion files (``.bvh``, ``.amc`` + ASF, ``.asf``): format, skeleton family, joints, frames, fps,
duration, the straightened ankle-hip-head chain length (``height_m``), how the joints map onto
human31 (``joint_map``, from the family's skeleton map or ``--skeleton-map``, else guessed from
the joint names: ``joint_map_source`` says which and ``guessed_joints`` lists the guessed ones),
and the human31 joints that cannot be mapped (``unmapped_joints``; ``ambiguous_joints`` lists
the candidates of names that fit twice). Camera files (Bouguet ``.cal``, OpenCV-style or
torchmocap ``.yaml``/``.yml``/``.json`` rigs): format and per-camera intrinsics/extrinsics in
metres. The output is strict JSON (no ``NaN``/``Infinity``). Unreadable input, or a file whose
numbers overflow: one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path
from typing import Any

__all__ = ["describe", "main", "to_json"]

_CAMERA_SUFFIXES = (".cal", ".json", ".yaml", ".yml")


def _round(x: float, nd: int = 6) -> float:
    return round(float(x), nd)


def _describe_motion(path: Path, asf: str | None, skeleton_map: str | None = None
                     ) -> dict[str, Any]:
    from torchmocap.io.errors import SkeletonMapError
    from torchmocap.io.load import load_motion
    from torchmocap.io.skeleton_maps import chain_height, joint_map_report

    clip = load_motion(path, asf=asf, skeleton_map=skeleton_map)
    is_asf_only = path.suffix.lower() == ".asf"
    try:
        height = _round(chain_height(clip, skeleton_map), 4)
    except SkeletonMapError:
        height = None
    report = joint_map_report(clip, skeleton_map)
    from torchmocap.io.trim import leading_reference_frames

    lead = 0 if is_asf_only else leading_reference_frames(clip).count
    return {
        "path": str(path),
        "format": path.suffix.lower().lstrip("."),
        "skeleton_family": clip.skeleton_family,
        "joints": clip.num_joints,
        "joint_names": clip.joint_names,
        "frames": 0 if is_asf_only else clip.num_frames,
        "fps": None if is_asf_only else _round(clip.fps, 4),
        "duration_s": 0.0 if is_asf_only else _round(clip.duration_s, 4),
        # leading frames holding a reference pose (skip_frames=auto drops them when tracking)
        "reference_frames": lead,
        "height_m": height,
        "unit_m": _round(clip.unit, 9),
        "joint_map_source": report["source"],
        "joint_map": report["joints"],
        "guessed_joints": report["guessed_joints"],
        "unmapped_joints": report["unmapped_joints"],
        "ambiguous_joints": report["ambiguous"],
    }


def _camera_fields(K, dist, R, t, size) -> dict[str, Any]:
    center = -(R.T @ t)
    return {
        "focal_px": [_round(K[0, 0]), _round(K[1, 1])],
        "principal_point_px": [_round(K[0, 2]), _round(K[1, 2])],
        "skew": _round(K[0, 1]),
        "K": [[_round(v) for v in row] for row in K.tolist()],
        "distortion": [_round(v, 9) for v in dist.tolist()],
        "R": [[_round(v, 9) for v in row] for row in R.tolist()],
        "t_m": [_round(v) for v in t.tolist()],
        "center_m": [_round(v) for v in center.tolist()],
        "image_size": [int(v) for v in size.tolist()],
    }


def _describe_camera(path: Path) -> dict[str, Any]:
    from torchmocap.cameras import read_bouguet_cal, read_rig

    if path.suffix.lower() == ".cal":
        c = read_bouguet_cal(path)
        cam = {
            "name": path.stem,
            **_camera_fields(c["K"], c["dist"], c["R"], c["t"], c["image_size"]),
        }
        return {"path": str(path), "format": "bouguet_cal", "cameras": [cam]}
    rig = read_rig(path)
    cams = []
    for i in range(rig.num_cameras):
        f = _camera_fields(
            rig.K[i].double(),
            rig.dist[i].double(),
            rig.R[i].double(),
            rig.t[i].double(),
            rig.image_size[i],
        )
        cams.append({"name": rig.names[i], **f})
    kind = "json" if path.suffix.lower() == ".json" else "yaml"
    return {"path": str(path), "format": f"camera_rig_{kind}", "cameras": cams}


def describe(path: str | Path, asf: str | None = None,
             skeleton_map: str | None = None) -> dict[str, Any]:
    """The JSON-able description printed by ``torchmocap-info``."""
    from torchmocap.io.load import MOTION_SUFFIXES

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix in MOTION_SUFFIXES:
        return _describe_motion(path, asf, skeleton_map)
    if skeleton_map is not None:
        raise ValueError(f"--skeleton-map: applies to motion files {MOTION_SUFFIXES}, not to "
                         f"{path.name}")
    if suffix in _CAMERA_SUFFIXES:
        return _describe_camera(path)
    raise ValueError(
        f"{path}: unsupported file type {suffix or '(none)'!r}; expected motion "
        f"{MOTION_SUFFIXES} or camera calibration {_CAMERA_SUFFIXES}"
    )


def _non_finite(obj: Any, where: str = "") -> tuple[str, float] | None:
    """The first (field, value) of ``obj`` that is a NaN or infinite float, else ``None``."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return where or "(top level)", obj
    if isinstance(obj, dict):
        items = obj.items()
    elif isinstance(obj, (list, tuple)):
        items = ((f"[{i}]", v) for i, v in enumerate(obj))
    else:
        return None
    for k, v in items:
        sub = f"{where}{k}" if str(k).startswith("[") else (f"{where}.{k}" if where else str(k))
        hit = _non_finite(v, sub)
        if hit is not None:
            return hit
    return None


def to_json(out: dict[str, Any]) -> str:
    """Strict JSON of a description; a NaN or infinity (e.g. a bone length that overflows) is a
    ``ValueError`` naming the field (``json`` would print ``Infinity``, which is not JSON)."""
    hit = _non_finite(out)
    if hit is not None:
        field, value = hit
        raise ValueError(f"{out.get('path', '')}: {field} is {value} (not a finite number): the "
                         "file's values are out of range")
    return json.dumps(out, indent=2, allow_nan=False)


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 unreadable input)."""
    parser = argparse.ArgumentParser(
        prog="torchmocap-info",
        description="Describe a motion file (BVH, ASF/AMC) or a camera calibration as JSON.",
    )
    parser.add_argument("path", help="motion (.bvh, .amc, .asf) or camera (.cal, .json, .yaml)")
    parser.add_argument("--asf", default=None, help="ASF skeleton of an AMC file")
    parser.add_argument("--skeleton-map", default=None, metavar="NAME|YAML",
                        help="skeleton map (built-in family name or map YAML) to map the "
                             "motion file's joints with, instead of the detected one")
    args = parser.parse_args(argv)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            out = describe(args.path, asf=args.asf, skeleton_map=args.skeleton_map)
            text = to_json(out)
        except Exception as e:  # noqa: BLE001 - any failure is reported as one line, exit 2
            msg = " ".join(str(e).split()) or type(e).__name__
            print(f"torchmocap-info: error: {msg}", file=sys.stderr)
            return 2
    for w in caught:
        print(f"torchmocap-info: warning: {' '.join(str(w.message).split())}", file=sys.stderr)
    try:
        print(text)
        sys.stdout.flush()
    except BrokenPipeError:  # e.g. piped into `head`
        sys.stderr.close()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
