"""Rebuild tests/data_files/ from the full recordings in ../shared/data (run from anywhere).

    python tests/data_files/make_data_files.py [--shared PATH]

What it writes (see README.md here for provenance and licences):

* ``mocap/``: every BVH and AMC of ``shared/data/mocap`` cut to a window of frames (bytes of
  the kept lines unchanged: channel orders, CRLF line ends and the Latin-1 header bytes of the
  HDM05 AMC files survive; a BVH's ``Frames:`` line gives the new count), the ASF files whole;
* ``multiview/bodytrack_sequenceB_1/``: the four calibrations whole, the grey images and
  foreground masks of frame 0 losslessly as PNG (``image0000.png``; the BMPs are 4x larger);
* ``body/makehuman_cc0/``: the CC0 MakeHuman mesh, weights and rig, xz-compressed
  (``*.xz``; ``tests/body/conftest.py`` unpacks them into a temporary folder);
* ``multiview/pose2sim_balancing/``: the calibration and licence whole, the OpenPose JSON files
  (raw and associated) of frames 0-9, the first 10 frames of every video (the compressed
  stream copied, not re-encoded: the decoded pixels are the original's), the background plates
  as JPEG (quality 88, full size) and the first 10 frames of Pose2Sim's raw TRC output.

The windows are chosen for what the tests read: e.g. frames 440-559 of ``131_01.bvh`` (mid
walk), 121 frames of ``01_01.bvh`` (its synthetic T-pose frame 0 and one second of data, the
frames of ``01_01.amc`` kept beside it).
"""

from __future__ import annotations

import argparse
import lzma
import re
import shutil
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_SHARED = HERE.parents[2] / "shared" / "data"

#: file -> (first frame, number of frames); files not listed keep frames 0..39
WINDOWS = {
    "cmu/131_01.bvh": (440, 120),
    "cmu/01_01.bvh": (0, 121),
    "cmu/01_01.amc": (0, 120),
    "cmu/60_12_scaled.bvh": (0, 100),
    "cmu/cmu21_kick.bvh": (0, 50),
    "hdm05/HDM_bk_hopBothLegs1hops_017_120.amc": (0, 100),
    # the whole file: the subject fit's wrong minimum in frames 58-70
    # (tests/data/subjects/test_mocap.py)
    "hdm05/HDM_bd_rotateArmsBothBackward1Reps_001_120.amc": (0, 90),
}
DEFAULT_WINDOW = (0, 40)


def _lines(raw: bytes) -> list[bytes]:
    return raw.splitlines(keepends=True)


def trim_bvh(raw: bytes, start: int, count: int) -> bytes:
    lines = _lines(raw)
    m = next(i for i, s in enumerate(lines) if s.strip().upper() == b"MOTION")
    body = [i for i in range(m + 1, len(lines)) if lines[i].strip()]
    i_frames, i_time, data = body[0], body[1], body[2:]
    assert lines[i_frames].strip().lower().startswith(b"frames")
    keep = data[start:start + count]
    assert len(keep) == count, f"only {len(data) - start} frames after {start}"
    end = re.search(rb"\r?\n$", lines[i_frames])
    frames_line = f"Frames: {count}".encode() + (end.group(0) if end else b"\n")
    return b"".join(lines[:i_frames] + [frames_line, lines[i_time]] + [lines[i] for i in keep])


def trim_amc(raw: bytes, start: int, count: int) -> bytes:
    assert start == 0, "AMC frames are numbered from 1: keep a prefix"
    lines = _lines(raw)
    frame_starts = [i for i, s in enumerate(lines) if s.strip().isdigit()]
    assert len(frame_starts) > count, f"only {len(frame_starts)} frames"
    return b"".join(lines[:frame_starts[count]])


def build(shared: Path, out: Path) -> None:
    src = shared / "mocap"
    for p in sorted(src.rglob("*")):
        if not p.is_file():
            continue
        rel = p.relative_to(src).as_posix()
        dst = out / "mocap" / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        start, count = WINDOWS.get(rel, DEFAULT_WINDOW)
        if p.suffix == ".bvh":
            dst.write_bytes(trim_bvh(p.read_bytes(), start, count))
        elif p.suffix == ".amc":
            dst.write_bytes(trim_amc(p.read_bytes(), start, count))
        elif p.suffix == ".asf":
            shutil.copyfile(p, dst)
    from PIL import Image

    bt = shared / "multiview" / "bodytrack_sequenceB_1"
    bt_out = out / "multiview" / "bodytrack_sequenceB_1"
    (bt_out / "CALIB").mkdir(parents=True, exist_ok=True)
    for i in range(1, 5):
        shutil.copyfile(bt / "CALIB" / f"Camera{i}.cal", bt_out / "CALIB" / f"Camera{i}.cal")
        for kind in ("CAM", "FG"):
            (bt_out / f"{kind}{i}").mkdir(exist_ok=True)
            with Image.open(bt / f"{kind}{i}" / "image0000.bmp") as im:
                im.save(bt_out / f"{kind}{i}" / "image0000.png", optimize=True)
    body, body_out = shared / "body" / "makehuman_cc0", out / "body" / "makehuman_cc0"
    body_out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(body / "LICENSE.md", body_out / "LICENSE.md")
    for name in ("base.obj", "basemesh_vertex_groups.json", "rig.cmu_mb.json",
                 "weights.cmu_mb.json"):
        (body_out / f"{name}.xz").write_bytes(
            lzma.compress((body / name).read_bytes(), preset=9 | lzma.PRESET_EXTREME))


#: frames of the pose2sim_balancing recording kept (0..POSE2SIM_FRAMES-1)
POSE2SIM_FRAMES = 10


def _ffmpeg() -> str:
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


def build_pose2sim(shared: Path, out: Path) -> None:
    import subprocess

    from PIL import Image

    src = shared / "multiview" / "pose2sim_balancing"
    dst = out / "multiview" / "pose2sim_balancing"
    for sub in ("calibration", "videos", "background", "pose2sim_output"):
        (dst / sub).mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "LICENSE", dst / "LICENSE")
    shutil.copyfile(src / "calibration" / "Calib.toml", dst / "calibration" / "Calib.toml")
    for kind in ("pose", "pose-associated"):
        for cam in sorted((src / kind).iterdir()):
            (dst / kind / cam.name).mkdir(parents=True, exist_ok=True)
            for f in sorted(cam.glob("*.json"))[:POSE2SIM_FRAMES]:
                shutil.copyfile(f, dst / kind / cam.name / f.name)
    for video in sorted((src / "videos").glob("*.mp4")):
        subprocess.run([_ffmpeg(), "-y", "-loglevel", "error", "-i", str(video), "-c", "copy",
                        "-frames:v", str(POSE2SIM_FRAMES), str(dst / "videos" / video.name)],
                       check=True)
    for plate in sorted((src / "background").glob("*.png")):
        with Image.open(plate) as im:
            im.convert("RGB").save(dst / "background" / f"{plate.stem}.jpg", quality=88)
    trc = src / "pose2sim_output" / "S00_P00_T01_BalancingTrial_0-100.trc"
    lines = trc.read_bytes().splitlines(keepends=True)
    head, rows = lines[:5], [r for r in lines[5:] if r.strip()][:POSE2SIM_FRAMES]
    fields = head[2].split(b"\t")
    fields[2] = fields[7] = str(POSE2SIM_FRAMES).encode()  # NumFrames, OrigNumFrames
    head[2] = b"\t".join(fields[:7]) + b"\t" + fields[7].strip() + \
        (b"\r\n" if head[2].endswith(b"\r\n") else b"\n")
    (dst / "pose2sim_output" / trc.name).write_bytes(b"".join(head + rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=DEFAULT_SHARED)
    args = ap.parse_args()
    build(args.shared, HERE)
    build_pose2sim(args.shared, HERE)
    total = sum(p.stat().st_size for p in HERE.rglob("*") if p.is_file())
    print(f"tests/data_files: {total / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
