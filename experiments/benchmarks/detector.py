"""The pose detector on real recordings: agreement with OpenPose, mask IoU, time per frame.

    python experiments/benchmarks/detector.py [--frames 100] [--one-core] [--out results.json]

* pose2sim_balancing (``../shared/data/multiview/pose2sim_balancing``, 4 views x 100 frames,
  1080x1920): MediaPipe Pose's keypoints against the OpenPose BODY_25B detections of the same
  frames (``pose-associated/``: the subject), per camera, the median pixel distance over the
  matched body keypoints (shoulders, elbows, wrists, hips, knees, ankles) and per group; frames
  whose median is over 50 px, and how many of them are a left/right swap (the swapped labelling
  is within 50 px); three ways to search: the whole image, a box from OpenPose's subject
  detections of the previous frame (what the loader gets from the other views), and a box from
  the detector's own previous frame (started from OpenPose's box at frame 0).
* bodytrack_sequenceB_1 (the vendored copy under tests/data_files): mask IoU (probability >
  0.5) against the shipped FG masks of the 4 views, and the share of landmarks inside them.
* where MediaPipe's keypoints lie relative to OpenPose's (the basis of the mediapipe_33
  keypoint map): both detectors' keypoints triangulated across the 4 views (DLT, the box from
  OpenPose), medians over the frames of widths, heights and distances.
* time per frame of ``MediaPipePoseDetector.detect`` (crop, model, mapping back), and of a
  :func:`~torchmocap.detectors.cached_detections` run that reads every frame from the cache.

``--one-core`` pins the process to one CPU core (the model's own thread pool then runs on it).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from torchmocap.detectors import MediaPipePoseDetector, cached_detections, keypoint_box
from torchmocap.io.frames import open_frames, read_mask
from torchmocap.io.openpose import KEYPOINT_FORMATS, read_openpose_json

REPO = Path(__file__).resolve().parents[2]
P2S = REPO.parent / "shared" / "data" / "multiview" / "pose2sim_balancing"
BODYTRACK = REPO / "tests" / "data_files" / "multiview" / "bodytrack_sequenceB_1"
MP, OP = KEYPOINT_FORMATS["mediapipe_33"], KEYPOINT_FORMATS["body_25b"]
BODY = ["LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist", "LHip", "RHip",
        "LKnee", "RKnee", "LAnkle", "RAnkle"]
GROUPS = {"head": ["Nose", "LEye", "REye", "LEar", "REar"], "shoulders": BODY[0:2],
          "elbows": BODY[2:4], "wrists": BODY[4:6], "hips": BODY[6:8], "knees": BODY[8:10],
          "ankles": BODY[10:12], "heels": ["LHeel", "RHeel"]}
SHARED = [n for n in MP if n in OP]


def _swap(name: str) -> str:
    return {"L": "R", "R": "L"}.get(name[0], "") + name[1:] if name[0] in "LR" else name


def distances(mp: torch.Tensor, op: torch.Tensor, swap: bool = False) -> dict[str, float]:
    """Pixel distance per shared keypoint name (OpenPose confidence > 0.1)."""
    out = {}
    for n in SHARED:
        j = OP.index(n)
        if op[j, 2] > 0.1:
            i = MP.index(_swap(n) if swap else n)
            out[n] = float((mp[i, :2] - op[j, :2]).norm())
    return out


def pose2sim(det: MediaPipePoseDetector, frames: int) -> tuple[dict, dict]:
    results, landmarks = {}, {}
    for cam in ("cam01", "cam02", "cam03", "cam04"):
        src = open_frames(P2S / "videos" / f"{cam}.mp4")
        op = [read_openpose_json(P2S / "pose-associated" / f"{cam}_json" / f"{cam}.{t:04d}.json",
                                 25) for t in range(frames)]
        rows = {m: [] for m in ("image", "box_openpose", "box_self")}
        found = {m: 0 for m in rows}
        times = {m: [] for m in rows}
        kps = {m: [] for m in rows}
        prev_self = None
        for t, rgb in enumerate(src.frames(0, frames)):
            ref = op[t][0] if len(op[t]) else None
            prev_op = op[t - 1] if t > 0 and len(op[t - 1]) else op[t]
            box_op = keypoint_box(prev_op[0]) if len(prev_op) else None
            for mode in rows:
                box = {"image": None, "box_openpose": box_op,
                       "box_self": box_op if prev_self is None else prev_self}[mode]
                t0 = time.perf_counter()
                out = det.detect(rgb, box)
                times[mode].append(time.perf_counter() - t0)
                kp = out.keypoints[0] if len(out.keypoints) else None
                kps[mode].append(kp.numpy() if kp is not None else np.full((33, 3), np.nan))
                found[mode] += kp is not None
                if mode == "box_self":
                    prev_self = keypoint_box(kp, 0.5) if kp is not None else None
                if kp is None or ref is None:
                    rows[mode].append(None)
                    continue
                rows[mode].append((distances(kp, ref), distances(kp, ref, swap=True)))
        res = {}
        for mode, rs in rows.items():
            body, groups, over, swapped, corrected = [], {g: [] for g in GROUPS}, 0, 0, []
            for r in rs:
                if r is None:
                    continue
                d, ds = r
                med = statistics.median([d[n] for n in BODY if n in d])
                meds = statistics.median([ds[n] for n in BODY if n in ds])
                body += [d[n] for n in BODY if n in d]
                corrected += [(ds if meds < med else d)[n] for n in BODY if n in d]
                for g, names in GROUPS.items():
                    groups[g] += [d[n] for n in names if n in d]
                if med > 50:
                    over += 1
                    swapped += meds <= 50
            res[mode] = {
                "frames": len(rs), "found": found[mode],
                "compared": sum(r is not None for r in rs),
                "median_px": statistics.median(body), "p90_px": float(np.percentile(body, 90)),
                "frames_over_50px": over, "of_them_left_right_swapped": swapped,
                "median_px_swaps_undone": statistics.median(corrected),
                "groups_median_px": {g: statistics.median(v) for g, v in groups.items() if v},
                "s_per_frame_median": statistics.median(times[mode][1:] or times[mode]),
                "s_first_frame": times[mode][0]}
        results[cam] = res
        landmarks[cam] = {m: np.stack(v) for m, v in kps.items()}
        print(cam, json.dumps({m: {k: v for k, v in r.items() if k != "groups_median_px"}
                               for m, r in res.items()}), flush=True)
    return results, landmarks


def bodytrack(det: MediaPipePoseDetector) -> dict:
    from PIL import Image

    out = {}
    for c in range(1, 5):
        with Image.open(BODYTRACK / f"CAM{c}" / "image0000.png") as im:
            rgb = np.asarray(im.convert("RGB"))
        fg = torch.from_numpy(read_mask(BODYTRACK / f"FG{c}" / "image0000.png"))
        d = det.detect(rgb)
        pm = d.mask > 0.5
        iou = float((pm & fg).sum() / (pm | fg).sum())
        uv = d.keypoints[0, :, :2].round().long() if len(d.keypoints) else None
        inside = None
        if uv is not None:
            u = uv[:, 0].clamp(0, fg.shape[1] - 1)
            v = uv[:, 1].clamp(0, fg.shape[0] - 1)
            inside = float(fg[v, u].float().mean())
        out[f"CAM{c}"] = {"found": len(d.keypoints), "iou": iou, "landmarks_in_mask": inside}
        print(f"bodytrack CAM{c}", out[f"CAM{c}"], flush=True)
    return out


def triangulated(landmarks: dict, frames: int) -> dict:
    """Medians (metres) over the frames of where MediaPipe's triangulated keypoints lie
    relative to OpenPose's: widths, height differences (world z up) and distances."""
    from torchmocap.cameras import read_calibration
    from torchmocap.cameras.triangulation import triangulate_dlt

    cams = ("cam01", "cam02", "cam03", "cam04")
    rig = read_calibration(P2S / "calibration" / "Calib.toml").double()
    mp = torch.tensor(np.stack([landmarks[c]["box_openpose"] for c in cams], 1))  # T C 33 3
    op = []
    for t in range(frames):
        row = []
        for c in cams:
            x = read_openpose_json(P2S / "pose-associated" / f"{c}_json" / f"{c}.{t:04d}.json", 25)
            row.append(x[0] if len(x) else torch.zeros(25, 3, dtype=torch.float64))
        op.append(torch.stack(row))
    op = torch.stack(op)

    def tri(x, min_conf):
        w = torch.nan_to_num(x[..., 2])
        return triangulate_dlt(torch.nan_to_num(x[..., :2]), torch.where(w > min_conf, w, 0 * w),
                               rig)

    X, Y = tri(mp, 0.5), tri(op, 0.3)
    m = lambda n: X[:, MP.index(n)]  # noqa: E731
    o = lambda n: Y[:, OP.index(n)]  # noqa: E731

    def med(v):
        v = v[torch.isfinite(v)]
        return round(float(v.median()), 4)

    def dist(a, b):
        return (a - b).norm(dim=-1)

    out = {}
    for pair in ("Hip", "Shoulder", "Ear", "Eye"):
        out[f"{pair.lower()} width mediapipe / openpose"] = (
            med(dist(m("L" + pair), m("R" + pair))), med(dist(o("L" + pair), o("R" + pair))))
    for n in ("LShoulder", "RShoulder", "LHip", "RHip", "LWrist", "RWrist", "LKnee", "RKnee",
              "LAnkle", "RAnkle", "LHeel", "RHeel"):
        out[f"{n}: distance, z of mediapipe - openpose"] = (med(dist(m(n), o(n))),
                                                            med((m(n) - o(n))[:, 2]))
    for s in "LR":
        out[f"{s}Heel from {s}Ankle (distance, z), mediapipe"] = (
            med(dist(m(s + "Heel"), m(s + "Ankle"))), med((m(s + "Heel") - m(s + "Ankle"))[:, 2]))
        out[f"{s}FootIndex from {s}Ankle / openpose {s}BigToe from {s}Ankle"] = (
            med(dist(m(s + "FootIndex"), m(s + "Ankle"))), med(dist(o(s + "BigToe"),
                                                                   o(s + "Ankle"))))
        for n in ("Pinky", "Index", "Thumb"):
            out[f"{s}{n} from {s}Wrist, mediapipe"] = med(dist(m(s + n), m(s + "Wrist")))
    for k, v in out.items():
        print(f"  {k}: {v}")
    return out


def cache_timing(frames: int) -> dict:
    """One camera through cached_detections: computing (and writing) every frame, then a
    second run that reads them all."""
    src = P2S / "videos" / "cam03.mp4"
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        a = cached_detections(src, {}, d, frames=range(frames), progress=False)
        t1 = time.perf_counter()
        b = cached_detections(src, {}, d, frames=range(frames), progress=False)
        t2 = time.perf_counter()
        assert len(a.computed) == frames and not b.computed
        size = sum(f.stat().st_size for f in Path(a.path).rglob("*") if f.is_file())
    return {"first_run_s_per_frame": (t1 - t0) / frames,
            "cached_run_s_per_frame": (t2 - t1) / frames, "entry_bytes_per_frame": size / frames}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--one-core", action="store_true", help="pin the process to one core")
    ap.add_argument("--out", type=Path, default=None, help="write the results as JSON")
    ap.add_argument("--landmarks", type=Path, default=None,
                    help="write the pose2sim landmarks (npz) for other analyses")
    args = ap.parse_args()
    if args.one_core:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    det = MediaPipePoseDetector()
    build = time.perf_counter() - t0
    res = {"build_s": build, "cores": len(os.sched_getaffinity(0)),
           "bodytrack": bodytrack(det)}
    res["pose2sim"], lms = pose2sim(det, args.frames)
    print("triangulated (metres):")
    res["triangulated"] = triangulated(lms, args.frames)
    res["cache"] = cache_timing(min(args.frames, 30))
    print(json.dumps(res["cache"]))
    if args.out:
        args.out.write_text(json.dumps(res, indent=1))
    if args.landmarks:
        np.savez_compressed(args.landmarks, **{f"{c}_{m}": v for c, r in lms.items()
                                               for m, v in r.items()})
    print("\n| camera | search | found | compared | median px | p90 px | "
          "frames > 50 px (L/R swaps) | median, swaps undone | ms/frame |\n"
          "|---|---|---|---|---|---|---|---|---|")
    for cam, r in res["pose2sim"].items():
        for mode, s in r.items():
            print(f"| {cam} | {mode} | {s['found']}/{s['frames']} | {s['compared']} | "
                  f"{s['median_px']:.1f} | "
                  f"{s['p90_px']:.1f} | {s['frames_over_50px']} "
                  f"({s['of_them_left_right_swapped']}) | {s['median_px_swaps_undone']:.1f} | "
                  f"{1000 * s['s_per_frame_median']:.1f} |")


if __name__ == "__main__":
    main()
