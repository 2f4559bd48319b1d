"""A real recording from its videos alone: the folder, and the report of the runs.

``prepare``: a recording folder holding only ``videos/`` and ``calibration/`` (symbolic links
to the files of the full recording; nothing else — no detections, masks or plates).

``report``: the runs of ``run.sh`` (``runs/<group>/<cam>``, one per held-out camera) scored on
one protocol:

* each run's own held-out score (``metrics.json`` ``heldout``: the track's mapped keypoints —
  the subject's fitted keypoint map — against the held-out view's detections of the run's own
  keypoint source, confidence > 0.3);
* every run against the same two detection sets of the held-out view: OpenPose's associated
  BODY_25B detections (``experiments/real_multiview/protocol.py``, the track's keypoints by
  the ``body_25b`` keypoint map) and MediaPipe's kept detections of that view (from the check
  with every view, by the ``mediapipe_33`` map) — the same frames, keypoints and threshold
  for every run;
* the held-out view's silhouette IoU of the track's capsule body against the detector's masks
  and against the masks computed by background subtraction (with the plates and OpenPose's
  keypoints, the OpenPose runs' masks), and the mask sets against each other;
* the detector's time per frame (a cold cache: decoding, detection, writing; and the
  detector's call alone on decoded frames).

Writes ``results/videos_alone.json`` and ``results/videos_alone.md``.

Usage (from the repository root)::

    python experiments/detector/videos_alone.py prepare
    bash experiments/detector/run.sh
    python experiments/detector/videos_alone.py report
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
RECORDING = ROOT.parent / "shared" / "data" / "multiview" / "pose2sim_balancing"
ALONE = ROOT / "outputs" / "videos_alone" / "pose2sim_balancing"
CACHE = ROOT / "outputs" / "keypoint_cache"
MASK_CACHE = ROOT / "outputs" / "mask_cache"
RUNS = HERE / "runs"
RESULTS = HERE / "results"
CAMERAS = ("cam01", "cam02", "cam03", "cam04")
GROUPS = {
    "openpose": "OpenPose files (pose-associated/) + computed masks (plates)",
    "mediapipe_detector": "videos alone: MediaPipe + detector masks",
    "mediapipe_compute": "videos alone: MediaPipe + computed masks (no plates)",
}
MIN_CONFIDENCE = 0.3
SCALE = 0.5

sys.path.insert(0, str(HERE.parent / "real_multiview"))


def prepare(recording: Path, out: Path) -> Path:
    """``out`` with ``videos/`` and ``calibration/`` linking to ``recording``'s files."""
    recording, out = Path(recording).resolve(), Path(out)
    for sub in ("videos", "calibration"):
        src = recording / sub
        if not src.is_dir():
            raise SystemExit(f"{src}: no such folder")
        (out / sub).mkdir(parents=True, exist_ok=True)
        for f in sorted(src.iterdir()):
            link = out / sub / f.name
            if link.is_symlink() or link.exists():
                if link.resolve() == f.resolve():
                    continue
                raise SystemExit(f"{link}: exists and is not a link to {f}")
            link.symlink_to(f)
    extra = [p.name for p in out.iterdir() if p.name not in ("videos", "calibration")]
    if extra:
        raise SystemExit(f"{out}: holds {extra} besides videos/ and calibration/")
    print(f"{out}: videos/ ({len(list((out / 'videos').iterdir()))} files), calibration/")
    return out


# --------------------------------------------------------------------------- reference data
def _load(path, **kw):
    from torchmocap.data.recordings import load_recording

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*codec's crop")
        return load_recording(path, scale=SCALE, **kw)


def full_size(j: torch.Tensor, scale: float) -> torch.Tensor:
    """Keypoints ``(..., K, 3)`` of the scaled images in full-size pixels."""
    j = j.double().clone()
    j[..., :2] = torch.where(j[..., 2:] > 0, (j[..., :2] + 0.5) / scale - 0.5, j[..., :2])
    return j


def references(cache: Path, mask_cache: Path) -> dict:
    """The mask sets and MediaPipe's detections of every view (no camera held out)."""
    det = _load(ALONE, keypoints={"source": "mediapipe", "cache": str(cache),
                                  "progress": False}, masks="detector")
    comp_mp = _load(ALONE, keypoints={"source": "mediapipe", "cache": str(cache),
                                      "progress": False}, masks="compute",
                    mask_cache=str(mask_cache))
    comp_op = _load(RECORDING, masks="compute", mask_cache=str(mask_cache))
    return {"mediapipe": full_size(det.joints2d, SCALE), "rig": det.rig,
            "masks": {"detector": det.silhouettes, "computed (MediaPipe, no plates)":
                      comp_mp.silhouettes, "computed (OpenPose, plates)": comp_op.silhouettes},
            "sizes": det.meta.image_sizes, "report": det.meta.keypoint_report}


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    """Mean over frames of the IoU of ``(T, H, W)`` masks (frames where both are empty: left
    out)."""
    inter = (a & b).flatten(1).sum(-1).double()
    union = (a | b).flatten(1).sum(-1).double()
    ok = union > 0
    return float((inter[ok] / union[ok]).mean())


# ---------------------------------------------------------------------------- runs
def track_skeleton(run: Path):
    """The run's tracking skeleton: human31 with the rest offsets of the run's ``tracked.bvh``
    (the subject's fitted skeleton, written with the track); :func:`check_skeleton` checks
    that it reproduces the file's joint positions."""
    from torchmocap.io import read_bvh
    from torchmocap.skeleton import Skeleton, human31

    clip = read_bvh(run / "tracked.bvh")
    spec = human31().to_dict()
    for j in spec["joints"]:
        j["offset"] = clip.offsets[clip.joint_names.index(j["name"])].tolist()
    return Skeleton.from_dict(spec).double()


def track_points(run: Path, kmap_name: str, names) -> torch.Tensor:
    """``(T, K, 3)`` the track's keypoints of the format ``kmap_name`` (template map on the
    track's skeleton; NaN where the map places none)."""
    from torchmocap.skeleton import keypoint_positions, load_keypoint_map

    sk = track_skeleton(run)
    with np.load(run / "track.npz") as z:
        theta = torch.from_numpy(z["theta"]).double()
    kmap = load_keypoint_map(kmap_name, sk)
    with torch.no_grad():
        kin = sk(theta)
        x = keypoint_positions(kin.positions, kin.rotations, kmap).double()
    out = torch.full((theta.shape[0], len(names), 3), math.nan, dtype=torch.float64)
    out[:, kmap.columns(list(names))] = x
    return out, sk, theta


def check_skeleton(run: Path) -> float:
    """Largest distance (m) between the rebuilt skeleton's joints and ``tracked.bvh``'s."""
    from torchmocap.io import read_bvh

    sk = track_skeleton(run)
    with np.load(run / "track.npz") as z:
        theta = torch.from_numpy(z["theta"]).double()
    clip = read_bvh(run / "tracked.bvh")
    with torch.no_grad():
        pos = sk(theta).positions
    ref = clip.global_positions().double()
    idx = [clip.joint_names.index(n) for n in sk.joint_names if n in clip.joint_names]
    mine = [sk.joint_names.index(n) for n in sk.joint_names if n in clip.joint_names]
    return float((pos[:, mine] - ref[:, idx]).norm(dim=-1).max())


def score_run(run: Path, ref: dict, openpose) -> dict:
    from protocol import heldout_scores

    from torchmocap.body import CapsuleBody
    from torchmocap.evaluation import reprojection_scores
    from torchmocap.io.openpose import keypoint_format
    from torchmocap.likelihoods.silhouette import render_capsule_silhouettes

    metrics = json.loads((run / "metrics.json").read_text())
    held = metrics["heldout"]
    cam = held["camera"]
    c = CAMERAS.index(cam)
    check = check_skeleton(run)
    if not check < 1e-4:
        raise ValueError(f"{run}: the rebuilt skeleton misses tracked.bvh's joints by "
                         f"{check:.3g} m")
    out = {"camera": cam, "seconds_per_frame": metrics.get("seconds_per_frame"),
           "own": {k: held.get(k) for k in ("median_px", "mean_px", "pck_05", "pck_10",
                                             "silhouette_iou", "num_compared")},
           "own_hold_first_pose_px": held["hold_first_pose"]["median_px"],
           "skeleton_check_m": check}
    X, sk, theta = track_points(run, "body_25b", keypoint_format("body_25b"))
    s = heldout_scores(X, openpose, c)
    out["vs_openpose"] = {"median_px": s.median_px, "mean_px": s.mean_px, "pck_05": s.pck_05,
                          "pck_10": s.pck_10, "compared": s.num_compared}
    Xm, _, _ = track_points(run, "mediapipe_33", keypoint_format("mediapipe_33"))
    rig = ref["rig"].double()
    full_rig = rig.scaled_images(1.0 / SCALE)
    s = reprojection_scores(Xm, ref["mediapipe"][:, c], full_rig.subset([c]), MIN_CONFIDENCE)
    out["vs_mediapipe"] = {"median_px": s.median_px, "mean_px": s.mean_px,
                           "pck_05": s.pck_05, "pck_10": s.pck_10, "compared": s.num_compared}
    body = CapsuleBody(sk.float())
    one = ref["rig"].subset([c])
    with torch.no_grad():
        sil = torch.stack([render_capsule_silhouettes(body, one, theta[t].float())[0]
                           for t in range(theta.shape[0])])
    out["silhouette_iou"] = {}
    h, w = sil.shape[-2:]  # the view's own size (the masks' canvas may be larger)
    for name, masks in ref["masks"].items():
        out["silhouette_iou"][name] = iou(sil, masks[:, c, :h, :w])
    return out


#: the body keypoints both detectors have
SHARED = ("LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist", "LHip", "RHip",
          "LKnee", "RKnee", "LAnkle", "RAnkle")


def detector_distance(mediapipe: torch.Tensor, openpose: torch.Tensor) -> torch.Tensor:
    """``(T,)`` per frame the median pixel distance between MediaPipe's kept body keypoints
    ``(T, 33, 3)`` and OpenPose's ``(T, 25, 3)`` (the names they share; NaN: none)."""
    from torchmocap.io.openpose import keypoint_format

    mp, op = keypoint_format("mediapipe_33"), keypoint_format("body_25b")
    a = mediapipe[:, [mp.index(n) for n in SHARED]]
    b = openpose[:, [op.index(n) for n in SHARED]]
    ok = (a[..., 2] > 0) & (b[..., 2] > 0.1)
    d = (a[..., :2] - b[..., :2]).norm(dim=-1)
    return torch.where(ok, d, torch.full_like(d, math.nan)).nanmedian(-1).values


def detector_timing(frames: int = 25) -> dict:
    """Milliseconds per frame of the detector's call on decoded 1080x1920 frames (whole
    image), per camera, after one untimed call."""
    from torchmocap.detectors import MediaPipePoseDetector
    from torchmocap.io.frames import open_frames

    out = {}
    with MediaPipePoseDetector() as det:
        for cam in CAMERAS:
            imgs = list(open_frames(RECORDING / "videos" / f"{cam}.mp4").frames(0, frames))
            det(imgs[0])
            t0 = time.perf_counter()
            for im in imgs:
                det(im)
            out[cam] = 1000 * (time.perf_counter() - t0) / len(imgs)
    return out


def cold_timing(tmp: Path) -> dict:
    """Seconds of the source's whole-image pass over every frame of every camera into an
    empty cache (decoding, detection, writing the JSON and mask PNGs), per frame."""
    from torchmocap.data.recordings.files import discover_recording
    from torchmocap.detectors import MediaPipePoseSettings, cached_detections

    files = discover_recording(ALONE)
    t0 = time.perf_counter()
    n = 0
    for cam in files.cameras:
        out = cached_detections(cam.frames, MediaPipePoseSettings(), tmp, progress=False)
        n += len(out.computed)
    return {"frames": n, "ms_per_frame": 1000 * (time.perf_counter() - t0) / n}


def report(args) -> None:
    import tempfile

    from protocol import load_detections

    openpose = load_detections(RECORDING)
    ref = references(Path(args.cache), Path(args.mask_cache))
    rows = {}
    for group in GROUPS:
        for cam in CAMERAS:
            run = RUNS / group / cam
            if not (run / "metrics.json").is_file():
                print(f"missing run {run}", file=sys.stderr)
                continue
            rows.setdefault(group, {})[cam] = score_run(run, ref, openpose)
    masks = ref["masks"]
    names = list(masks)
    pairs = {}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            pairs[f"{a} vs {b}"] = {cam: iou(masks[a][:, c], masks[b][:, c])
                                    for c, cam in enumerate(CAMERAS)}
    kp_report = ref["report"]
    checks = {cam: {k: v[k] for k in ("frames_dropped", "frames_relabelled",
                                      "frames_searched_in_box", "frames_unchecked",
                                      "median_agreement_px")}
              for cam, v in kp_report["views"].items()}
    for c, cam in enumerate(CAMERAS):
        d = detector_distance(ref["mediapipe"][:, c], openpose.points[:, c])
        ok = d[torch.isfinite(d)]
        checks[cam]["vs_openpose_median_px"] = float(ok.median())
        checks[cam]["vs_openpose_frames_over_50px"] = int((ok > 50).sum())
    import os

    timing = {"load_average_before": list(os.getloadavg()),
              "detect_ms_per_frame": detector_timing()}
    with tempfile.TemporaryDirectory() as tmp:
        timing["cold_cache"] = cold_timing(Path(tmp))
    timing["load_average_after"] = list(os.getloadavg())
    result = {"runs": rows, "mask_iou": pairs, "keypoint_check": checks, "timing": timing,
              "groups": GROUPS}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "videos_alone.json").write_text(json.dumps(result, indent=1))
    (RESULTS / "videos_alone.md").write_text(table(result))
    print(table(result))


def _f(x, d=1):
    return "–" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{d}f}"


def table(r: dict) -> str:
    lines = ["# From the videos alone: results", "",
             "Held-out median pixel error (full-size pixels, confidence > 0.3) per held-out "
             "camera, and the mean of the four.", ""]
    cols = [("own", "own detections"), ("vs_openpose", "vs OpenPose"),
            ("vs_mediapipe", "vs MediaPipe")]
    lines.append("| run | scored against | " + " | ".join(CAMERAS) + " | mean | PCK@5 % "
                 "(mean) | s/frame |")
    lines.append("|---|---|" + "---:|" * (len(CAMERAS) + 3))
    for group, label in r["groups"].items():
        rows = r["runs"].get(group, {})
        if not rows:
            continue
        for key, what in cols:
            med = [rows[c][key]["median_px"] if c in rows else None for c in CAMERAS]
            pck = [rows[c][key]["pck_05"] for c in CAMERAS if c in rows]
            sec = [rows[c]["seconds_per_frame"] for c in CAMERAS if c in rows]
            ok = [m for m in med if m is not None]
            lines.append(f"| {label} | {what} | " + " | ".join(_f(m) for m in med) +
                         f" | {_f(np.mean(ok) if ok else None)} | "
                         f"{_f(100 * np.mean(pck) if pck else None)} | "
                         f"{_f(np.mean(sec) if sec else None, 2)} |")
    lines += ["", "Held-out silhouette IoU of the track's capsule body (mean over frames and "
              "the four held-out cameras) against each mask set:", "",
              "| run | " + " | ".join(next(iter(next(iter(r["runs"].values())).values()))
                                      ["silhouette_iou"]) + " |",
              "|---|" + "---:|" * 3]
    for group, label in r["groups"].items():
        rows = r["runs"].get(group, {})
        if not rows:
            continue
        sets = next(iter(rows.values()))["silhouette_iou"]
        lines.append(f"| {label} | " + " | ".join(
            _f(np.mean([rows[c]["silhouette_iou"][k] for c in rows]), 3) for k in sets) + " |")
    lines += ["", "Mask sets against each other (IoU, mean over the 100 frames):", "",
              "| masks | " + " | ".join(CAMERAS) + " |", "|---|" + "---:|" * len(CAMERAS)]
    for k, v in r["mask_iou"].items():
        lines.append(f"| {k} | " + " | ".join(_f(v[c], 3) for c in CAMERAS) + " |")
    lines += ["", "The cross-view check of MediaPipe's detections (every view, 100 frames):", "",
              "| camera | dropped | relabelled (left/right) | searched in the subject's box | "
              "median agreement px | median px from OpenPose's detections | frames > 50 px |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for cam, v in r["keypoint_check"].items():
        lines.append(f"| {cam} | {len(v['frames_dropped'])} | {len(v['frames_relabelled'])} | "
                     f"{len(v['frames_searched_in_box'])} | {_f(v['median_agreement_px'])} | "
                     f"{_f(v.get('vs_openpose_median_px'))} | "
                     f"{v.get('vs_openpose_frames_over_50px', '–')} |")
    t = r["timing"]
    lines += ["", "Detector time per 1080x1920 frame (one thread, the shared machine): "
              + ", ".join(f"{c} {_f(v)} ms" for c, v in t["detect_ms_per_frame"].items())
              + f" (the call alone); {_f(t['cold_cache']['ms_per_frame'])} ms per frame "
              f"through an empty cache ({t['cold_cache']['frames']} frames: decoding, "
              "detection, writing); load average "
              + " → ".join(f"{t[k][0]:.1f}" for k in ("load_average_before",
                                                      "load_average_after") if k in t)
              + " on the 2 cores.", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("prepare")
    a.add_argument("--recording", default=str(RECORDING))
    a.add_argument("--out", default=str(ALONE))
    b = sub.add_parser("report")
    b.add_argument("--cache", default=str(CACHE))
    b.add_argument("--mask-cache", default=str(MASK_CACHE))
    args = p.parse_args(argv)
    if args.cmd == "prepare":
        prepare(Path(args.recording), Path(args.out))
    else:
        report(args)


if __name__ == "__main__":
    main()
