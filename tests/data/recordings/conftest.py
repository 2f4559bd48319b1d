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


def scale_camera(root: Path, cam: str, factor: float) -> None:
    """Camera ``cam``'s calibration for images scaled by ``factor`` (size and intrinsics,
    the pixel-centre convention ``u' + 0.5 = factor (u + 0.5)``)."""
    def fn(text):
        parts = _sections(text)
        i = next(i for i, s in enumerate(parts) if s.startswith(f"[{cam}]"))
        sec = parts[i]
        w, h = (float(v) for v in re.search(r"size = \[([^\]]*)\]", sec).group(1).split(","))
        K = [float(v) for v in re.findall(r"[-\d.e+]+", re.search(
            r"matrix = (\[.*\]\])", sec).group(1))]
        fx, cx, fy, cy = (K[0] * factor, (K[2] + 0.5) * factor - 0.5, K[4] * factor,
                          (K[5] + 0.5) * factor - 0.5)
        sec = re.sub(r"size = \[[^\]]*\]", f"size = [ {w * factor}, {h * factor}]", sec)
        sec = re.sub(r"matrix = \[.*\]\]", f"matrix = [ [ {fx}, 0.0, {cx}], [ 0.0, {fy}, "
                     f"{cy}], [ 0.0, 0.0, 1.0]]", sec)
        parts[i] = sec
        return "".join(parts)
    _edit_toml(root, fn)


def set_size(root: Path, cam: str, size: tuple[int, int]) -> None:
    def fn(text):
        parts = _sections(text)
        i = next(i for i, s in enumerate(parts) if s.startswith(f"[{cam}]"))
        parts[i] = re.sub(r"size = \[[^\]]*\]", f"size = [ {size[0]}.0, {size[1]}.0]", parts[i])
        return "".join(parts)
    _edit_toml(root, fn)


def half_size_video(root: Path, cam: str) -> None:
    """Re-encode ``videos/<cam>.mp4`` at half its size (H.264)."""
    import subprocess

    import imageio_ffmpeg

    src = root / "videos" / f"{cam}.mp4"
    tmp = root / "videos" / f"{cam}.half.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error",
                    "-y", "-i", str(src), "-vf", "scale=iw/2:ih/2", "-c:v", "libx264",
                    "-crf", "18", "-pix_fmt", "yuv420p", str(tmp)], check=True)
    tmp.replace(src)
    from PIL import Image

    for plate in (root / "background").glob(f"{cam}*"):
        with Image.open(plate) as im:
            im.resize((im.width // 2, im.height // 2)).save(plate)


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
        shutil.copytree(src, root, ignore=shutil.ignore_patterns("pose2sim_output"))
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
        elif kind == "half_resolution_camera":  # cam04 recorded at 544x960, calibrated so
            half_size_video(root, "cam04")
            scale_camera(root, "cam_04", 0.5)
            map_keypoints(root, "cam04", lambda u, v, c: ((u + 0.5) / 2 - 0.5,
                                                          (v + 0.5) / 2 - 0.5, c))
        elif kind == "calibration_4k":  # cam03 calibrated on 2176x3840 images
            scale_camera(root, "cam_03", 2.0)
        elif kind == "size_12px":  # cam03's calibration 12 columns wider than its frames
            set_size(root, "cam_03", (1100, 1920))
        elif kind == "png_video":
            from PIL import Image

            Image.new("RGB", (1080, 1920)).save(root / "videos" / "frame.png")
            (root / "videos" / "frame.png").replace(root / "videos" / "cam02.mp4")
        elif kind != "intact":
            raise ValueError(kind)
        return root

    return make
