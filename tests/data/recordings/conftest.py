"""Broken copies of the trimmed pose2sim_balancing recording, each corrupted the way real
recordings are (``broken(kind)``): calibrations exchanged or in another unit, detections
exchanged, shifted, emptied or of half-size images, an image folder with a gap."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest


def _sections(text: str) -> list[str]:
    return re.split(r"(?m)^(?=\[)", text)


def _edit_toml(root: Path, fn) -> None:
    p = root / "calibration" / "Calib.toml"
    p.write_text(fn(p.read_text()))


def swap_calibrations(root: Path, a: str = "cam_01", b: str = "cam_02") -> None:
    """Exchange the entries of cameras ``a`` and ``b`` (their names stay)."""
    def fn(text):
        parts = _sections(text)
        ia = next(i for i, s in enumerate(parts) if s.startswith(f"[{a}]"))
        ib = next(i for i, s in enumerate(parts) if s.startswith(f"[{b}]"))
        parts[ia], parts[ib] = parts[ib].replace(b, a), parts[ia].replace(a, b)
        return "".join(parts)
    _edit_toml(root, fn)


def scale_translations(root: Path, factor: float) -> None:
    def fn(text):
        def rep(m):
            vals = [float(v) * factor for v in m.group(1).split(",")]
            return "translation = [ " + ", ".join(repr(v) for v in vals) + "]"
        return re.sub(r"translation = \[([^\]]*)\]", rep, text)
    _edit_toml(root, fn)


def set_translation(root: Path, cam: str, t: tuple[float, float, float]) -> None:
    def fn(text):
        parts = _sections(text)
        i = next(i for i, s in enumerate(parts) if s.startswith(f"[{cam}]"))
        values = ", ".join(repr(float(x)) for x in t)
        parts[i] = re.sub(r"translation = \[[^\]]*\]", f"translation = [ {values}]", parts[i])
        return "".join(parts)
    _edit_toml(root, fn)


def edit_people(root: Path, cam: str, fn) -> None:
    """Apply ``fn(people) -> people`` to every keypoint file of ``cam`` (both folders)."""
    for kind in ("pose-associated", "pose"):
        for p in sorted((root / kind / f"{cam}_json").glob("*.json")):
            data = json.loads(p.read_text())
            data["people"] = fn(data["people"])
            p.write_text(json.dumps(data))


def map_keypoints(root: Path, cam: str, fn) -> None:
    """Apply ``fn(u, v, c) -> (u, v, c)`` to every detected keypoint of ``cam``."""
    def people(ps):
        for person in ps:
            k = person.get("pose_keypoints_2d", [])
            for i in range(0, len(k), 3):
                if k[i + 2] > 0:
                    k[i], k[i + 1], k[i + 2] = fn(k[i], k[i + 1], k[i + 2])
        return ps
    edit_people(root, cam, people)


def swap_detections(root: Path, a: str = "cam01", b: str = "cam02") -> None:
    for kind in ("pose-associated", "pose"):
        da, db, tmp = (root / kind / f"{a}_json", root / kind / f"{b}_json",
                       root / kind / "exchange")
        da.rename(tmp)
        db.rename(da)
        tmp.rename(db)
        for d, (old, new) in ((da, (b, a)), (db, (a, b))):
            for p in d.glob("*.json"):
                p.rename(d / p.name.replace(old, new))


def to_image_folders(root: Path, stop: int) -> None:
    """The videos as image folders ``images/<cam>/000000.jpg ...`` (first ``stop`` frames)."""
    from PIL import Image

    from torchmocap.io.frames import VideoFrames

    for v in sorted((root / "videos").glob("*.mp4")):
        out = root / "images" / v.stem
        out.mkdir(parents=True)
        for t, frame in enumerate(VideoFrames(v).frames(0, stop, 1, 1.0)):
            Image.fromarray(frame).save(out / f"{t:06d}.jpg", quality=90)
    shutil.rmtree(root / "videos")


@pytest.fixture
def broken(tmp_path, shared_data):
    """``broken(kind)``: a copy of the trimmed recording corrupted by ``kind``."""
    src = shared_data / "multiview" / "pose2sim_balancing"

    def make(kind: str = "intact") -> Path:
        root = tmp_path / kind
        shutil.copytree(src, root, ignore=shutil.ignore_patterns("pose2sim_output",
                                                                 "background"))
        if kind == "millimetres":
            scale_translations(root, 1000.0)
        elif kind == "calibrations_exchanged":
            swap_calibrations(root)
        elif kind == "detections_exchanged":
            swap_detections(root)
        elif kind == "camera_far":
            set_translation(root, "cam_02", (1e6, 1e6, 1e6))
        elif kind == "outside":
            map_keypoints(root, "cam02", lambda u, v, c: (u + 1e5, v - 1e5, c))
        elif kind == "half_size":
            map_keypoints(root, "cam02", lambda u, v, c: (u / 2, v / 2, c))
        elif kind == "confidences":
            map_keypoints(root, "cam02", lambda u, v, c: (u, v, 3 * c))
        elif kind == "nobody":
            edit_people(root, "cam02", lambda people: [])
        elif kind == "nobody_anywhere":
            for cam in ("cam01", "cam02", "cam03", "cam04"):
                edit_people(root, cam, lambda people: [])
        elif kind == "image_gap":
            to_image_folders(root, 5)
            (root / "images" / "cam02" / "000002.jpg").unlink()
        elif kind != "intact":
            raise ValueError(kind)
        return root

    return make
