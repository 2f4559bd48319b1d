"""The synthetic data source of the command lines (``data=default``): :func:`synthesized_sequence`
reads a motion clip (or the bundled CMU walk), fits the subject and synthesises observations
under a scenario. Real recordings have their own sources (:mod:`torchmocap.data.recordings`).
Relative paths are read from the working directory.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["BUNDLED_CLIP_NAME", "CLIP_KEYS", "DataConfigError", "body_model", "bundled_clip_path",
           "check_seed", "clip_name",
           "synthesized_sequence"]

#: the settings of ``data.clip`` (every one is in ``conf/data/clip/bundled.yaml``, so each can
#: be overridden on the command line without ``+``)
CLIP_KEYS = frozenset({"name", "path", "asf", "skeleton_map", "unit", "up", "fps",
                       "skip_frames", "start", "frames", "in_place"})


#: frames kept by ``data.clip.frames: auto`` (3 s at 25 fps; fewer when the clip is shorter)
AUTO_FRAMES = 75
#: label of the bundled clip (``data/clip/bundled.yaml``)
BUNDLED_CLIP_NAME = "bundled_walk"


class DataConfigError(ValueError):
    """A data setting is invalid (names the ``data.*`` key)."""


def bundled_clip_path() -> Path:
    """The package's bundled 3 s CMU 131_01 walk (BVH)."""
    from importlib import resources

    return Path(str(resources.files("torchmocap") / "assets" / "clips" / "cmu_131_01_walk.bvh"))


def _path(value, key: str) -> str | None:
    if value is None or str(value) in ("", "null", "None"):
        return None
    p = Path(str(value)).expanduser().absolute()
    if not p.exists():
        raise FileNotFoundError(f"{key}: no such file: {p}")
    return str(p)


def body_model(skeleton: str | None = None):
    """The :class:`~torchmocap.skeleton.Skeleton` of ``data.skeleton``: human31 for ``None``,
    else the YAML at that path, which must have human31's joints and DoFs (in its order: the
    IMU placement, the skinning and the trackers' per-DoF settings name them)."""
    from torchmocap.skeleton import Skeleton, human31

    ref = human31()
    path = _path(skeleton, "data.skeleton")
    if path is None:
        return ref
    from torchmocap.inputs import note_input

    note_input(path)
    try:
        sk = Skeleton.from_yaml(path)
    except Exception as e:  # malformed YAML or skeleton spec
        raise DataConfigError(f"data.skeleton: cannot read a skeleton from {path}: {e}") from e
    zero = [n for n, o in zip(sk.joint_names[1:], sk.offsets[1:]) if float(o.norm()) == 0.0]
    if zero:  # a bone's direction is its rest offset: the subject fit needs every one
        raise DataConfigError(f"data.skeleton: {path}: joints {zero} have a zero offset; every "
                              "bone needs a rest direction (human31's offsets scaled, not zeroed)")
    for what, got, want in (("joints", sk.joint_names, ref.joint_names),
                            ("DoFs", sk.dof_names, ref.dof_names)):
        if list(got) != list(want):
            diff = sorted(set(want) ^ set(got)) or "the same names in another order"
            raise DataConfigError(
                f"data.skeleton: expected human31's {what} in its order (a copy of "
                f"torchmocap/skeleton/presets/human31.yaml with other limits or offsets), "
                f"{path} differs: {diff}")
    return sk


def check_seed(value, key: str = "seed") -> int:
    """``value`` as a seed: an integer (``1.5``, ``True`` or ``"3"`` are errors naming ``key``;
    ``int()`` would silently turn 1.5 into 1, the run of another seed)."""
    import numbers

    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise DataConfigError(f"{key}: expected an integer seed, got {value!r}")
    return int(value)


def _number(value, key: str, what: str, minimum: float, strict: bool) -> float:
    ok = (not isinstance(value, bool) and isinstance(value, (int, float))
          and math.isfinite(value) and (value > minimum if strict else value >= minimum))
    if not ok:
        raise DataConfigError(f"{key}: expected {what}, got {value!r}")
    return float(value)


def _int(value, key: str, minimum: int, allow_none: bool = False) -> int | None:
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise DataConfigError(f"{key}: expected an integer >= {minimum}"
                              f"{' or null' if allow_none else ''}, got {value!r}")
    return value


def _short_map(joint_map: Mapping[str, str], n: int = 4) -> str:
    items = [f"{h}={v}" for h, v in joint_map.items()]
    return ", ".join(items[:n]) + (f", ... {len(items) - n} more" if len(items) > n else "")


def _check_memory(motion, fps: float, frames: int | None, sc) -> None:
    """Refuse a clip whose resampling or synthesis needs more memory than is available: the
    resampled motion (rotations and translations of every joint, float64) and the synthesised
    images and masks (``frames`` x cameras x pixels x 3 and 1 bytes; ``frames`` None: all)."""
    from torchmocap.data.synthetic.scenario import build_rig
    from torchmocap.memory import check_memory

    n = int(motion.num_frames * fps / motion.fps) + 1
    T = n if frames is None else min(frames, n)
    cams = build_rig(sc.rig, sc.image_size).num_cameras
    w, h = (int(v) for v in sc.image_size)
    per_pixel = 3 * bool(sc.images.enabled) + bool(sc.silhouettes.enabled)
    need = n * motion.num_joints * 12 * 8 + T * cams * w * h * per_pixel
    check_memory(need, f"{n} frames of the motion at {fps:g} fps and the images of {T} frames "
                 f"of {cams} {w}x{h} views", "data.clip.fps / data.clip.frames")


def clip_name(clip: Mapping[str, Any]) -> str:
    """The label of ``clip`` in reports: its ``name``, or the file's stem when it has none.

    The bundled clip preset's label (``bundled_walk``) names only the bundled file: with
    ``data.clip.path=<file>`` and no ``data.clip.name`` the file's stem is used, so that runs of
    different files are not reported under the bundled walk's name.
    """
    name = clip.get("name")
    path = _path(clip.get("path"), "data.clip.path")
    if path is None:
        return str(name) if name else BUNDLED_CLIP_NAME
    if not name or (name == BUNDLED_CLIP_NAME
                    and Path(path).resolve() != bundled_clip_path().resolve()):
        return Path(path).stem
    return str(name)


def synthesized_sequence(clip: Mapping[str, Any], scenario: str = "studio",
                         scenario_overrides: Mapping[str, Any] | None = None, seed: int = 0,
                         min_frames: int = 2, skeleton: str | None = None):
    """Clip -> fitted human31 subject -> observations synthesised under ``scenario``.

    Args:
        clip: ``name`` (a label for run directories and reports), ``path`` (BVH/AMC/ASF;
            null = the bundled walk), ``asf`` (skeleton of an AMC),
            ``skeleton_map`` (family name or map YAML; null = auto-detected), ``unit`` (metres
            per file length unit; null = the map's, else inferred from the subject's size —
            :func:`~torchmocap.io.units.infer_length_unit`), ``up`` (the file's up axis:
            ``auto`` turns a clip whose rest pose does not stand along +z upright, ``y``, ``z``
            — :func:`~torchmocap.io.upright.upright`), ``fps`` (resample
            to; null = the scenario's), ``skip_frames`` (leading source frames to drop, or
            ``auto``: those holding a reference pose rather than motion, e.g. the T-pose frame
            0 of the cgspeed CMU BVH — :func:`~torchmocap.io.trim.leading_reference_frames`),
            ``start`` (seconds to skip after resampling), ``frames`` (frames to keep —
            ``auto``: up to :data:`AUTO_FRAMES`, all of a shorter clip; null = all; a number
            more than the clip has after ``start`` is an error), ``in_place`` (hold the
            root at its first-frame position and orientation: the person stands in place).
        scenario: bundled scenario name or YAML path
            (:func:`~torchmocap.data.synthetic.load_scenario`).
        scenario_overrides: dotted or nested scenario keys to replace, e.g.
            ``{"imu.misalignment_deg": [5, 10], "body": "capsules"}``.
        seed: seed of the synthesis (an integer; 1.5 is an error, not seed 1).
        min_frames: fewest frames accepted (a tracker needs 2).
        skeleton: YAML of the body model to fit and track (null = human31 as shipped): human31's
            joints and DoFs with other joint limits or proportions, e.g. a copy of
            ``torchmocap/skeleton/presets/human31.yaml`` with wider ``limits_deg`` (the subject
            fit still sets the bone lengths from the clip).
    Returns:
        a :class:`~torchmocap.data.Sequence` with ``meta.clip`` describing the source
        (``guessed_joints``: the human31 joints mapped by name guessing when no skeleton map
        matches the file; a warning says so).
    """
    from torchmocap.data.subjects.mocap import fit_subject
    from torchmocap.data.synthetic import load_scenario, synthesize
    from torchmocap.data.synthetic.scenario import MAX_FPS
    from torchmocap.io import load_motion
    from torchmocap.io.units import check_subject_size

    unknown = sorted(set(clip) - CLIP_KEYS)
    if unknown:
        raise DataConfigError(f"data.clip: unknown keys {unknown}; expected {sorted(CLIP_KEYS)}")
    base = body_model(skeleton)
    path = _path(clip.get("path"), "data.clip.path") or str(bundled_clip_path())
    asf = _path(clip.get("asf"), "data.clip.asf")
    smap = clip.get("skeleton_map")
    if smap and Path(str(smap)).expanduser().is_file():
        smap = str(Path(str(smap)).expanduser().absolute())
    unit = clip.get("unit")
    if unit is not None:
        unit = _number(unit, "data.clip.unit", "metres per file length unit (> 0) or null", 0,
                       True)
    from torchmocap.io.upright import UP_AXES

    up = clip.get("up") or "auto"
    if up not in UP_AXES:
        raise DataConfigError(f"data.clip.up: expected one of {list(UP_AXES)}, got {up!r}")
    skip = clip.get("skip_frames") or 0
    if skip != "auto" and (isinstance(skip, bool) or not isinstance(skip, int) or skip < 0):
        raise DataConfigError(f"data.clip.skip_frames: expected an integer >= 0 or 'auto', got "
                              f"{skip!r}")
    frames = clip.get("frames")
    auto_frames = frames == "auto"
    if not auto_frames:
        if isinstance(frames, str):
            raise DataConfigError(f"data.clip.frames: expected an integer >= {min_frames}, "
                                  f"'auto' or null, got {frames!r}")
        frames = _int(frames, "data.clip.frames", min_frames, allow_none=True)
    in_place = clip.get("in_place", False)
    if not isinstance(in_place, bool):
        raise DataConfigError(f"data.clip.in_place: expected true or false, got {in_place!r}")
    start = clip.get("start")
    start = 0.0 if start is None else _number(start, "data.clip.start", "seconds >= 0", 0, False)
    fps_cfg = clip.get("fps")
    if fps_cfg is not None:
        _number(fps_cfg, "data.clip.fps", "a finite frame rate > 0 or null", 0, True)
        if fps_cfg > MAX_FPS:
            raise DataConfigError(f"data.clip.fps: expected at most {MAX_FPS:g} fps (the images "
                                  f"of every frame are synthesised and held), got {fps_cfg!r}")
    if asf is not None and Path(path).suffix.lower() != ".amc":
        raise DataConfigError(f"data.clip.asf: only an .amc clip reads a separate skeleton, "
                              f"data.clip.path is {Path(path).name} (set data.clip.asf=null)")
    seed = check_seed(seed, "data.seed")
    sc_name = str(scenario)
    if sc_name.endswith((".yaml", ".yml")):
        sc_name = str(Path(sc_name).expanduser().absolute())
    sc = load_scenario(sc_name, **dict(scenario_overrides or {}))
    motion = load_motion(path, asf=asf, unit=unit, skip_frames=0 if skip == "auto" else skip,
                         skeleton_map=smap, up=up)
    if skip == "auto":
        from torchmocap.io.trim import trim_reference_frames

        motion, lead = trim_reference_frames(motion, Path(path).name)
        skip = lead.count
    check_subject_size(motion, smap, "data.clip.unit")
    fps = float(fps_cfg) if fps_cfg is not None else float(sc.fps)
    _check_memory(motion, fps, AUTO_FRAMES if auto_frames else frames, sc)
    file_frames, file_fps = motion.num_frames, motion.fps
    if abs(motion.fps - fps) > 1e-6:
        motion = motion.resample(fps)
    a = int(round(float(start) * fps))
    if a >= motion.num_frames:
        raise DataConfigError(f"data.clip.start: {start} s is past the clip's end "
                              f"({motion.num_frames / fps:.2f} s)")
    available = motion.num_frames - a
    if available < min_frames:
        rate = (f" (the file: {file_frames} at {file_fps:g} fps; data.clip.fps={file_fps:g} "
                "keeps its rate)" if abs(file_fps - fps) > 1e-6 else "")
        raise DataConfigError(f"data.clip: the clip has {available} frame(s) after start "
                              f"{start:g} s at {fps:g} fps{rate}; tracking needs at least "
                              f"{min_frames}: use a longer clip or an earlier data.clip.start")
    if auto_frames:
        frames = min(AUTO_FRAMES, available)
    if frames is not None and frames > available:
        raise DataConfigError(f"data.clip.frames: {frames} frames requested but the clip has "
                              f"{available} frames after start {start:g} s at {fps:g} fps "
                              f"(set data.clip.frames <= {available}, or null for all)")
    end = motion.num_frames if frames is None else a + frames
    if end - a < min_frames:
        raise DataConfigError(f"data.clip: only {end - a} frames after start {start} s; "
                              f"need >= {min_frames}")
    if a > 0 or end < motion.num_frames:
        motion = motion.slice(a, end)
    if in_place:
        motion = motion.in_place()
    subject = fit_subject(motion, skeleton_map=smap, base=base)
    seq = synthesize(subject, sc, seed=seed)
    seq.meta.skeleton = _path(skeleton, "data.skeleton") or "human31"
    seq.meta.clip = {"name": clip_name(clip), "path": path, "asf": asf,
                        "skeleton_map": smap, "unit": motion.unit, "skip_frames": skip,
                        "start": float(start),
                        "in_place": in_place,
                        "fps": fps, "frames": seq.num_frames, "family": subject.family,
                        "guessed_joints": subject.info.get("guessed_joints", [])}
    if subject.info.get("guessed_joints"):
        import warnings

        warnings.warn(f"data.clip.path: no skeleton map matches {Path(path).name}; its joints "
                      f"were mapped onto human31 by their names "
                      f"({_short_map(subject.info.get('joint_map', {}))}) - pass "
                      "data.clip.skeleton_map=<map YAML> if that is wrong", stacklevel=2)
    return seq
