"""The bad and unusual recordings of the reliability review, tried through the command line
(``torchmocap-track data=recording tracker=real_keypoints data.scale=0.25 data.stop=4
evaluation.heldout_camera=cam01 ...`` on a corrupted copy of the trimmed pose2sim_balancing):
exit status, the error or warnings, the held-out score; writes ``results/cases.md``.

    python experiments/recording_checks/cases.py [--data tests/data_files] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from margins import (  # noqa: E402
    _keypoints,
    far_camera,
    millimetres,
    swap_calibrations,
    swap_detections,
)

EXE = str(Path(sys.executable).parent / "torchmocap-track")


def _nobody(root, cams=("cam02",)):
    for cam in cams:
        for kind in ("pose-associated", "pose"):
            for p in (root / kind / f"{cam}_json").glob("*.json"):
                p.write_text(json.dumps({"version": 1.3, "people": []}))


def _images(root, stop=5, gap=None):
    from PIL import Image

    from torchmocap.io.frames import VideoFrames

    for v in sorted((root / "videos").glob("*.mp4")):
        out = root / "images" / v.stem
        out.mkdir(parents=True)
        for t, frame in enumerate(VideoFrames(v).frames(0, stop, 1, 1.0)):
            Image.fromarray(frame).save(out / f"{t:06d}.jpg", quality=90)
    shutil.rmtree(root / "videos")
    if gap:
        (root / "images" / gap).unlink()


def _png_video(root):
    from PIL import Image

    Image.new("RGB", (1080, 1920)).save(root / "videos" / "x.png")
    (root / "videos" / "x.png").replace(root / "videos" / "cam02.mp4")


def _toml(root, fn):
    p = root / "calibration" / "Calib.toml"
    p.write_text(fn(p.read_text()))


def _section(cam, fn):
    def edit(text):
        parts = re.split(r"(?m)^(?=\[)", text)
        i = next(i for i, s in enumerate(parts) if s.startswith(f"[{cam}]"))
        parts[i] = fn(parts[i])
        return "".join(parts)
    return edit


def _size(root, cam, w, h):
    _toml(root, _section(cam, lambda s: re.sub(r"size = \[[^\]]*\]", f"size = [ {w}, {h}]", s)))


def _rotation(root, cam, value):
    _toml(root, _section(cam, lambda s: re.sub(r"rotation = \[.*\]", f"rotation = {value}", s)))


def _calibration_4k(root):
    def fn(s):
        K = [float(v) for v in re.findall(r"[-\d.e+]+", re.search(r"matrix = (\[.*\]\])",
                                                                  s).group(1))]
        fx, cx, fy, cy = 2 * K[0], 2 * (K[2] + 0.5) - 0.5, 2 * K[4], 2 * (K[5] + 0.5) - 0.5
        s = re.sub(r"size = \[[^\]]*\]", "size = [ 2176.0, 3840.0]", s)
        return re.sub(r"matrix = \[.*\]\]", f"matrix = [ [ {fx}, 0.0, {cx}], [ 0.0, {fy}, "
                      f"{cy}], [ 0.0, 0.0, 1.0]]", s)
    _toml(root, _section("cam_03", fn))


CASES = [
    ("intact", None, []),
    ("1. translations x 1000", millimetres, []),
    ("2. cam_01 <-> cam_02 calibrations", swap_calibrations, []),
    ("3. cam01 <-> cam02 detections", swap_detections, []),
    ("4. cam_02 at (1e6, 1e6, 1e6) m", far_camera, []),
    ("5. cam02 keypoints + (1e5, -1e5) px", lambda r: _keypoints(
        r, "cam02", lambda u, v, c: (u + 1e5, v - 1e5, c)), []),
    ("5. cam02 keypoints of half-size images", lambda r: _keypoints(
        r, "cam02", lambda u, v, c: (u / 2, v / 2, c)), []),
    ("5. cam02 confidences x 3", lambda r: _keypoints(
        r, "cam02", lambda u, v, c: (u, v, 3 * c)), []),
    ("6. images/cam02/000002.jpg missing", lambda r: _images(r, gap="cam02/000002.jpg"),
     ["data.fps=60"]),
    ("7. nobody in cam02, cam01 held out", _nobody, []),
    ("7. nobody in cam02, cam03 held out", _nobody, ["evaluation.heldout_camera=cam03"]),
    ("nobody in any view", lambda r: _nobody(r, ("cam01", "cam02", "cam03", "cam04")), []),
    ("8. run folder under a file", None, ["hydra.run.dir=a_file/run"]),
    ("data.cameras=[cam02]", None, ["data.cameras=[cam02]", "evaluation.heldout_camera=null"]),
    ("two cameras, one held out", None, ["data.cameras=[cam01,cam02]"]),
    ("a PNG named cam02.mp4", _png_video, []),
    ("cam_03 calibrated on 2176x3840 images", _calibration_4k, []),
    ("cam_03 size 1100x1920 (12 px)", lambda r: _size(r, "cam_03", 1100, 1920), []),
    ("cam_02 rotation of 4 values", lambda r: _rotation(r, "cam_02", "[ 1.0, 0.0, 0.0, 1.0]"),
     []),
    ("cam_02 rotation not a rotation", lambda r: _rotation(
        r, "cam_02", "[ [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]]"), []),
    ("data.scale=0.02", None, ["data.scale=0.02"]),
]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(HERE.parents[1] / "tests" / "data_files"))
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args()
    src = Path(args.data) / "multiview" / "pose2sim_balancing"
    rows = ["| input | exit | error, or warnings (codec crops left out) | held-out cam median px "
            "/ IoU | tracked views median px | tracked IoU |", "|---|---|---|---|---|---|"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "a_file").write_text("")
        for k, (name, fn, extra) in enumerate(CASES):
            root = tmp / f"rec{k}"
            shutil.copytree(src, root, ignore=shutil.ignore_patterns("pose2sim_output"))
            if fn is not None:
                fn(root)
            run = tmp / f"run{k}"
            cmd = [EXE, "data=recording", "tracker=real_keypoints", f"data.path={root}",
                   "data.scale=0.25", "data.stop=4", "evaluation.heldout_camera=cam01",
                   "threads=1", "progress=false", "glb.enabled=false", "overlays=0",
                   f"data.mask_cache={tmp / 'masks'}", f"hydra.run.dir={run}", *extra]
            r = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp, env=env,
                               timeout=600)
            lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
            tb = any("Traceback" in ln for ln in lines)
            errors = [ln.split("error: ", 1)[1] for ln in lines if "error: " in ln]
            warned = [ln.split("warning: ", 1)[1] for ln in lines if "warning: " in ln
                      and "codec's crop" not in ln]
            said = errors or warned
            said = [re.sub(r"/tmp/\S*?/rec\d+/?", "", re.sub(r" \(/tmp[^)]*\)", "", s))
                    for s in said]
            text = ("TRACEBACK " if tb else "") + ("; ".join(s[:230] for s in said) or "silent")
            held = tracked = iou_t = "-"
            m = run / "metrics.json"
            if m.is_file():
                mm = json.loads(m.read_text())
                h = mm.get("heldout") or {}
                iou = h.get("silhouette_iou")
                med = h.get("median_px")
                held = (f"{h.get('camera')} {'-' if med is None else f'{med:.1f}'} / "
                        f"{'-' if iou is None else f'{iou:.2f}'}")
                t_iou = (mm.get("silhouette_iou") or {}).get("mean_over_frames")
                iou_t = "-" if t_iou is None else f"{t_iou:.2f}"
                tracked = ", ".join(
                    f"{c} {'-' if v['median_px'] is None else round(v['median_px'], 1)}"
                    for c, v in (mm.get("tracked_views") or {}).items())
            rows.append(f"| {name} | {r.returncode} | {text.replace('|', '/')} | {held} | "
                        f"{tracked} | {iou_t} |")
            print(rows[-1], flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "cases.md").write_text("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
