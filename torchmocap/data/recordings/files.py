"""Where the files of a multi-view recording are: :func:`discover_recording`.

A recording folder holds (names are case-sensitive; ``<cam>`` is a camera's name)::

    calibration/Calib.toml            Pose2Sim / anipose TOML           (one of these
    calibration/intri.yml, extri.yml  OpenCV / EasyMocap (or at the top)  calibrations,
    CALIB/Camera<i>.cal               Bouguet .cal files (bodytrack)      see read_calibration)
    videos/<cam>.mp4                  a video per camera (.mp4 .avi .mov .mkv .webm .m4v), or
    images/<cam>/                     a folder of images per camera, or
    CAM<i>/                           bodytrack's image folders
    pose-associated/<cam>_json/       OpenPose JSON of the subject alone (optional), and/or
    pose/<cam>_json/                  OpenPose JSON of everyone detected (optional)
    masks/<cam>/  or  FG<i>/          foreground masks, one image per frame (optional)
    background/<cam>*.png|jpg         background plates (optional; reported, not read)

The cameras are those with frames (videos or image folders). The other files are matched to
them by :func:`~torchmocap.cameras.camera_key` — the number in the name — so ``cam01.mp4``,
``pose/cam01_json``, ``FG1`` and a calibration entry ``cam_01`` or ``Camera1`` all belong to
camera 1. A ``_json`` suffix of keypoint folders is ignored.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from torchmocap.cameras import calibration_files, camera_key
from torchmocap.io.frames import IMAGE_SUFFIXES, VIDEO_SUFFIXES, natural_key

__all__ = ["RecordingCamera", "RecordingFiles", "RecordingLayoutError", "discover_recording"]

#: folders searched for a calibration, in this order
CALIBRATION_FOLDERS = ("calibration", "CALIB", ".")
#: the folders of a recording whose entries are searched for cameras' files
SEARCHED_FOLDERS = ("videos", "images", "pose-associated", "pose", "masks", "background")


class RecordingLayoutError(FileNotFoundError):
    """A recording folder lacks a file it needs, or holds conflicting ones (names them)."""


@dataclass
class RecordingCamera:
    """The files of one camera.

    Attributes:
        name: the camera's name (video stem or image folder name).
        frames: its video file or image folder.
        keypoints: keypoint folders by kind (``"associated"``, ``"raw"``).
        masks: its mask folder, or None.
        background: its background plates.
    """

    name: str
    frames: Path
    keypoints: dict[str, Path] = field(default_factory=dict)
    masks: Path | None = None
    background: list[Path] = field(default_factory=list)

    @property
    def key(self) -> str:
        return camera_key(self.name)


@dataclass
class RecordingFiles:
    """The files of a recording: its folder, calibration path, and cameras in name order."""

    root: Path
    calibration: Path
    cameras: list[RecordingCamera]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]


def _by_key(items: dict[str, Path], what: str) -> dict[str, Path]:
    """``{camera_key(name): path}``, refusing two entries of one camera."""
    out: dict[str, Path] = {}
    for name, path in sorted(items.items(), key=lambda kv: natural_key(kv[0])):
        k = camera_key(name)
        if k in out:
            raise RecordingLayoutError(f"{what}: {out[k]} and {path} are the same camera "
                                       f"({k!r}); keep one")
        out[k] = path
    return out


def _frame_sources(root: Path) -> dict[str, Path]:
    found: dict[str, Path] = {}
    videos = root / "videos"
    if videos.is_dir():
        for p in videos.iterdir():
            if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
                found.setdefault(p.stem, p)
                if found[p.stem] != p:
                    raise RecordingLayoutError(f"{videos}: two videos of camera {p.stem!r} "
                                               f"({found[p.stem].name}, {p.name})")
    images = root / "images"
    if images.is_dir():
        for d in images.iterdir():
            if d.is_dir():
                if d.name in found:
                    raise RecordingLayoutError(f"camera {d.name!r} has both {found[d.name]} "
                                               f"and {d}; keep one")
                found[d.name] = d
    for d in root.glob("CAM*"):
        if d.is_dir() and d.name[3:].isdigit():
            found[d.name] = d
    return found


def _calibration(root: Path) -> Path:
    where = [(root / f).resolve() for f in CALIBRATION_FOLDERS
             if calibration_files(root / f)]
    if not where:
        raise RecordingLayoutError(
            f"{root}: no calibration (looked in {', '.join(CALIBRATION_FOLDERS)} for a .toml "
            "file, intri.yml + extri.yml, or Bouguet *.cal files)")
    if len(where) > 1:
        raise RecordingLayoutError(f"{root}: calibrations in several folders {where}; keep one")
    return where[0]


def discover_recording(path: str | os.PathLike) -> RecordingFiles:
    """Find the calibration and the cameras' files of a recording folder (module docstring).

    Raises:
        RecordingLayoutError: no such folder, no calibration or calibrations in several
            folders, no camera frames, two files for one camera, or keypoints or masks of a
            camera without frames (its video is missing).
    """
    from torchmocap.inputs import note_input

    root = Path(path).expanduser().absolute()
    if not root.is_dir():
        raise RecordingLayoutError(f"data.path: no such recording folder: {root}")
    # the folders searched here decide what is read (a mask folder added is a change)
    for d in (root, *(root / s for s in SEARCHED_FOLDERS)):
        if d.is_dir():
            note_input(d)
    calib = _calibration(root)
    sources = _by_key(_frame_sources(root), f"{root}: camera frames")
    if not sources:
        raise RecordingLayoutError(
            f"{root}: no camera frames (expected videos/<cam>.mp4, images/<cam>/ or CAM<i>/)")
    keypoints = {}
    for kind, folder in (("associated", "pose-associated"), ("raw", "pose")):
        d = root / folder
        dirs = {p.name.removesuffix("_json"): p for p in d.iterdir() if p.is_dir()} \
            if d.is_dir() else {}
        keypoints[kind] = _by_key(dirs, str(d))
    masks_dirs = {p.name: p for p in (root / "masks").iterdir() if p.is_dir()} \
        if (root / "masks").is_dir() else {}
    masks_dirs.update({p.name: p for p in root.glob("FG*") if p.is_dir() and
                       p.name[2:].isdigit()})
    masks = _by_key(masks_dirs, f"{root}: masks")
    plates: dict[str, list[Path]] = {}
    bg = root / "background"
    if bg.is_dir():
        for p in sorted(bg.iterdir(), key=lambda q: natural_key(q.name)):
            if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
                plates.setdefault(camera_key(p.stem), []).append(p)
    for what, folders in (("keypoints", keypoints["associated"]),
                          ("keypoints", keypoints["raw"]), ("masks", masks)):
        for k, d in folders.items():
            if k not in sources:
                raise RecordingLayoutError(
                    f"{d}: {what} of a camera without frames (expected videos/<cam>.mp4, "
                    f"images/<cam>/ or CAM<i>/ for camera {k!r}; cameras with frames: "
                    f"{sorted(p.name for p in sources.values())})")
    cams = []
    for k, frames in sorted(sources.items(), key=lambda kv: natural_key(kv[1].stem)):
        cams.append(RecordingCamera(
            name=frames.stem if frames.is_file() else frames.name, frames=frames,
            keypoints={kind: d[k] for kind, d in keypoints.items() if k in d},
            masks=masks.get(k), background=plates.get(k, [])))
    return RecordingFiles(root, calib, cams)
