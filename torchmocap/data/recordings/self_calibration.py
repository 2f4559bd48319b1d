"""Self-calibration of a recording: its rig refined from the subject's own detections before
tracking (``data.calibration``), and the refined calibration written beside a run.

Two objectives (``data.calibration.objective``):

* ``bundle`` — :func:`~torchmocap.cameras.bundle_adjust`: a 3D point free per frame and
  keypoint (fast; a calibration any tool can use);
* ``model`` — the bundle adjustment, then :func:`~torchmocap.ik.fit_rig_to_skeleton`: the
  points are the subject's skeleton keypoints (constant bones, the keypoint map's offsets,
  smooth motion), its poses refined jointly with the cameras. The subject is fitted
  (:func:`~torchmocap.ik.fit_keypoint_subject`) to the refined frames' triangulation under the
  bundle-adjusted rig.

The refinement sees every loaded camera, the held-out one included (its calibration is what
its score depends on): with a held-out camera, refine on frames that are not tracked
(``data.calibration.frames`` outside ``data.start``..``data.stop``), or the held-out score
is optimistic — the loader warns when they overlap.

Refined time offsets (``time_offset`` in the groups) resample each view's detections onto the
subject's clock (:func:`shift_detections`); images and masks are not resampled.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from torchmocap.data.settings import with_defaults

__all__ = ["CALIBRATION_DEFAULTS", "OBJECTIVES", "calibration_settings", "refine_range",
           "refine_rig", "shift_detections", "write_refinement"]

#: the ``data.calibration`` settings and their defaults
CALIBRATION_DEFAULTS: dict[str, Any] = {
    "file": None, "refine": False, "frames": None, "groups": ["rotation", "translation"],
    "objective": "bundle", "priors": {}, "loss": {}, "max_time_offset": 5.0,
    "trajectory_acceleration": 50.0, "iterations": 200, "progress": True,
}
OBJECTIVES = ("bundle", "model")
#: refined frames by default: the first half of the loaded frames, at most this many
DEFAULT_MAX_FRAMES = 300
#: fewest refined frames
MIN_FRAMES = 4


def _positive(name: str, v, integer: bool = False) -> None:
    bad = isinstance(v, bool) or not isinstance(v, int if integer else (int, float)) or \
        not math.isfinite(v) or v <= 0
    if bad:
        what = "an int >= 1" if integer else "a number > 0"
        raise ValueError(f"data.calibration.{name}: expected {what}, got {v!r}")


def calibration_settings(given: Mapping[str, Any] | None) -> dict[str, Any]:
    """The checked ``data.calibration`` settings (defaults filled in).

    Raises:
        ValueError: an unknown key or a bad value, naming ``data.calibration.<key>``.
    """
    from torchmocap.cameras import RefinementError, RigPriors, RobustLoss
    from torchmocap.cameras.rig_parameters import check_groups

    s = with_defaults("data.calibration", given, CALIBRATION_DEFAULTS)
    if s["file"] is not None and not isinstance(s["file"], str):
        raise ValueError(f"data.calibration.file: expected a calibration file or folder "
                         f"(a path), or null, got {s['file']!r}")
    if not isinstance(s["refine"], bool):
        raise ValueError(f"data.calibration.refine: expected true or false, got "
                         f"{s['refine']!r}")
    if s["objective"] not in OBJECTIVES:
        raise ValueError(f"data.calibration.objective: expected one of {list(OBJECTIVES)}, got "
                         f"{s['objective']!r}")
    f = s["frames"]
    if f is not None:
        f = list(f) if hasattr(f, "__iter__") and not isinstance(f, (str, Mapping)) else f
        if not isinstance(f, list) or len(f) != 2 or any(
                isinstance(x, bool) or not isinstance(x, int) for x in f) or f[0] < 0 or \
                f[1] <= f[0]:
            raise ValueError(f"data.calibration.frames: expected [start, stop] frame numbers "
                             f"with 0 <= start < stop, or null, got {s['frames']!r}")
        s["frames"] = f
    groups = s["groups"]
    if isinstance(groups, str):
        groups = [groups]
    try:
        s["groups"] = list(check_groups(list(groups)))
    except (RefinementError, TypeError) as e:
        raise ValueError(f"data.calibration.groups: {e}") from None
    for key, cls in (("priors", RigPriors), ("loss", RobustLoss)):
        try:
            s[key] = cls.from_dict(dict(s[key] or {})).to_dict()
        except (RefinementError, TypeError) as e:
            raise ValueError(f"data.calibration.{key}: {e}") from None
    _positive("max_time_offset", s["max_time_offset"])
    _positive("trajectory_acceleration", s["trajectory_acceleration"])
    _positive("iterations", s["iterations"], integer=True)
    if not isinstance(s["progress"], bool):
        raise ValueError(f"data.calibration.progress: expected true or false, got "
                         f"{s['progress']!r}")
    return s


def refine_range(settings: Mapping[str, Any], loaded: range, length: int) -> range:
    """The recording's frames refined: ``data.calibration.frames`` (``[start, stop)``, frame
    numbers of the recording, not of the loaded range), or by default the first half of the
    loaded frames (at most :data:`DEFAULT_MAX_FRAMES`).

    Raises:
        ValueError: a range outside the recording's ``length`` frames, or shorter than
            :data:`MIN_FRAMES` (named ``data.calibration.frames``).
    """
    f = settings["frames"]
    if f is None:
        a = loaded.start
        n = max(MIN_FRAMES, min(DEFAULT_MAX_FRAMES, (loaded.stop - loaded.start) // 2))
        f = [a, min(length, a + n)]
    if f[1] > length:
        raise ValueError(f"data.calibration.frames: [{f[0]}, {f[1]}] reaches beyond the "
                         f"recording's {length} frames (0..{length - 1})")
    if f[1] - f[0] < MIN_FRAMES:
        raise ValueError(f"data.calibration.frames: [{f[0]}, {f[1]}] has {f[1] - f[0]} frames; "
                         f"refining needs at least {MIN_FRAMES}")
    return range(f[0], f[1])


def _subject_poses(detections, rig, fmt: str, names, keypoint_map, max_error_px: float):
    """The subject (skeleton, keypoint map) and a pose per frame, fitted to the frames'
    triangulation: frames with too few triangulated keypoints take the nearest fitted pose."""
    from torchmocap.cameras import triangulate_robust
    from torchmocap.ik import fit_keypoint_subject

    det = detections.double()
    X, used = triangulate_robust(det[..., :2], det[..., 2], rig, max_error_px)
    ok = torch.isfinite(X).all(-1).sum(-1) >= 4
    fitted = [t for t in range(det.shape[0]) if bool(ok[t])]
    if len(fitted) < MIN_FRAMES:
        raise ValueError(f"data.calibration: {len(fitted)} refined frames have 4 keypoints "
                         f"seen by two views; the model objective needs {MIN_FRAMES}")
    fit = fit_keypoint_subject(X[fitted], used[fitted].mean(1), keypoint_map or fmt,
                               keypoint_names=list(names))
    idx = torch.tensor(fitted)
    nearest = (torch.arange(det.shape[0])[:, None] - idx[None]).abs().argmin(1)
    return fit, fit.theta[nearest]


def refine_rig(detections: torch.Tensor, rig, keypoint_names, fmt: str,
               settings: Mapping[str, Any], fps: float, frames: range,
               subject: Mapping[str, Any] | None = None):
    """Refine ``rig`` from the detections of the refined frames.

    Args:
        detections: ``(T, C, K, 3)`` of the refined frames, in ``rig``'s pixels (full size).
        rig: the given calibration (full size).
        keypoint_names, fmt: the detections' columns and format.
        settings: :func:`calibration_settings`.
        fps: the recording's frame rate.
        frames: the recording's refined frame numbers (for the record).
        subject: ``data.subject`` settings (the model objective's ``keypoint_map`` and
            ``max_error_px``).

    Returns:
        ``(refined rig, record)``: the record is JSON-ready — ``objective``, ``frames``,
        ``groups``, ``seconds``, ``time_offsets`` (frames per camera), ``report``
        (:func:`~torchmocap.cameras.refinement_report`: per camera rotation ° / centre mm /
        focal % / principal point px / time offset ± std, residuals before → after),
        and, with the model objective, ``bundle_report`` (the first stage).

    Raises:
        ValueError: the refinement's own errors, named ``data.calibration``.
    """
    from torchmocap.cameras import RefinementError, bundle_adjust
    from torchmocap.data.subjects.recorded import subject_settings
    from torchmocap.ik import fit_rig_to_skeleton

    t0 = time.perf_counter()
    rig64 = rig.double()
    temporal = "time_offset" in settings["groups"]
    try:
        res = bundle_adjust(
            detections.double(), rig64, groups=settings["groups"], priors=settings["priors"],
            loss=settings["loss"], max_time_offset=settings["max_time_offset"], fps=fps,
            trajectory_acceleration=settings["trajectory_acceleration"] if temporal else None,
            max_iterations=settings["iterations"])
    except RefinementError as e:
        raise ValueError(f"data.calibration: {e} (refined frames {frames.start}.."
                         f"{frames.stop - 1})") from None
    record: dict[str, Any] = {"objective": settings["objective"],
                              "frames": [frames.start, frames.stop],
                              "groups": list(settings["groups"])}
    if settings["objective"] == "model":
        sub = subject_settings(subject)
        fit, theta = _subject_poses(detections, res.rig.double(), fmt, keypoint_names,
                                    sub["keypoint_map"], float(sub["max_error_px"]))
        record["bundle_report"] = res.report()
        try:
            res, _ = fit_rig_to_skeleton(
                detections.double(), rig64, fit.skeleton, fit.keypoint_map, theta,
                keypoint_names, groups=settings["groups"], priors=settings["priors"],
                loss=settings["loss"], noise_px=res.noise_px, fps=fps,
                trajectory_acceleration=settings["trajectory_acceleration"],
                iterations=settings["iterations"], start_values=res.values,
                progress=settings["progress"])
        except RefinementError as e:
            raise ValueError(f"data.calibration: {e}") from None
    refined = res.rig.float() if rig.K.dtype == torch.float32 else res.rig
    refined.names = list(rig.names)
    record["seconds"] = round(time.perf_counter() - t0, 3)
    record["time_offsets"] = [round(float(v), 4) for v in res.time_offsets]
    record["report"] = res.report()
    return refined, record


def shift_detections(joints2d: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Detections resampled onto the subject's clock.

    Camera ``c``'s frame ``t`` shows the subject at ``t + δ_c``; the detection of the subject
    at time ``t`` in camera ``c`` is read at its fractional frame ``t − δ_c`` by linear
    interpolation of the two nearest frames (a keypoint missed in either is missed; outside
    the frames the nearest frame's).

    Args:
        joints2d: ``(T, C, K, 3)`` (u, v, confidence).
        offsets: ``(C,)`` offsets ``δ_c`` in frames of ``joints2d``.

    Returns:
        ``(T, C, K, 3)`` of ``joints2d``'s dtype.
    """
    T = joints2d.shape[0]
    out = joints2d.clone()
    for c, d in enumerate(offsets.tolist()):
        if d == 0.0:
            continue
        s = (torch.arange(T, dtype=torch.float64) - d).clamp(0, T - 1)
        i0 = s.floor().long().clamp(max=T - 1)
        i1 = (i0 + 1).clamp(max=T - 1)
        u = (s - i0.to(s)).to(joints2d.dtype)[:, None, None]
        a, b = joints2d[i0, c], joints2d[i1, c]
        uv = (1 - u) * a[..., :2] + u * b[..., :2]
        both = (a[..., 2] > 0) & ((b[..., 2] > 0) | (u[..., 0] == 0))
        conf = torch.where(u[..., 0] == 0, a[..., 2], torch.minimum(a[..., 2], b[..., 2]))
        out[:, c] = torch.where(both[..., None], torch.cat([uv, conf[..., None]], -1),
                                torch.zeros_like(a))
    return out


def warn_overlap(frames: range, loaded: range, heldout: str | None) -> None:
    """Warn when the held-out camera's detections on tracked frames refine the rig."""
    overlap = range(max(frames.start, loaded.start), min(frames.stop, loaded.stop))
    if heldout is not None and len(overlap):
        warnings.warn(f"data.calibration.frames [{frames.start}, {frames.stop}) overlap the "
                      f"tracked frames [{loaded.start}, {loaded.stop}): the held-out camera "
                      f"{heldout!r}'s detections there refined the rig and are scored (the "
                      "score is optimistic); refine on frames that are not tracked",
                      stacklevel=3)


def write_refinement(out: str | Path, rig, record: Mapping[str, Any], calibration: str | Path,
                     unit: str | float | None = None) -> list[Path]:
    """Write a refined calibration and its report into ``out/calibration/``.

    The calibration in the given one's format: a TOML (Pose2Sim / anipose) as
    ``<name>_refined.toml``, intri/extri YAML as ``intri.yml`` + ``extri.yml``; a Bouguet
    calibration (no writer) as ``Calib_refined.toml``. Beside it ``refinement.md`` (the
    per-camera table) and ``refinement.json`` (the record). Every file atomically.

    Args:
        out: the run (or output) folder.
        rig: the refined rig at the calibration's own image size.
        record: :func:`refine_rig`'s record.
        calibration: the given calibration file (its format and name).
        unit: the recording's ``data.unit`` (None: metres).

    Returns:
        the files written.
    """
    from torchmocap.atomic import write_json_atomic, write_text_atomic
    from torchmocap.cameras import calibration_files, report_markdown, write_calibration

    folder = Path(out) / "calibration"
    folder.mkdir(parents=True, exist_ok=True)
    src = Path(calibration)
    if src.is_dir():  # the recording's calibration folder: the file it holds
        kinds = calibration_files(src)
        src = next(iter(kinds.values()))[0] if len(kinds) == 1 else src / "Calib.toml"
    if src.suffix.lower() == ".toml":
        target = folder / f"{src.stem}_refined.toml"
    elif src.suffix.lower() in (".yml", ".yaml") and src.stem.lower() in ("intri", "extri"):
        target = folder / f"intri{src.suffix}"
    else:
        target = folder / "Calib_refined.toml"
    written = list(write_calibration(rig, target, unit or "m"))
    table = report_markdown(record["report"])
    text = (f"# Refined calibration ({record['objective']} objective, frames "
            f"{record['frames'][0]}–{record['frames'][1] - 1}, groups "
            f"{', '.join(record['groups'])})\n\nGiven: `{src}`. Refined: "
            f"{', '.join(f'`{p.name}`' for p in written)}.\n\n{table}\n")
    written.append(write_text_atomic(folder / "refinement.md", text))
    write_json_atomic(dict(record), folder / "refinement.json")
    written.append(folder / "refinement.json")
    return written
