"""Refining the recording's calibration from the subject's own detections, scored on frames
the refinement did not see.

For each split (refine on frames 0–59, score on 60–99; refine on 40–99, score on 0–39) and
each set of refined parameter groups:

1. :func:`torchmocap.cameras.bundle_adjust` on the refined frames of all four cameras (3D
   points free per frame and keypoint, DLT start; Cauchy loss, 20 px; detections of confidence
   > 0.3 weighted by confidence; the default priors; the mean gauge);
2. leave one camera out on the scored frames, with the given and with the refined rig: the
   other three views' detections of confidence > 0.3, confidence-weighted DLT
   (:func:`torchmocap.cameras.triangulate_dlt`, this folder's ``peers.dlt``), projected into
   the held-out camera and compared with its detections of confidence > 0.3
   (:func:`torchmocap.evaluation.leave_one_camera_out`; median px per camera, and their mean).

With time offsets refined, the held-out score uses the refined rig alone (the DLT of the
other views at the frame's own time): the offsets are reported with their uncertainties.

Writes ``results/calibration_refinement.md`` (tables) and ``results/calibration_refinement.json``
(every number, the per-camera reports). Command (from the repository root)::

    OMP_NUM_THREADS=1 python experiments/real_multiview/calibration_refinement.py

``--recording`` another recording folder, ``--splits`` e.g. ``0:60/60:100``, ``--groups``
``rotation,translation,focal`` (repeatable), ``--out`` the results folder.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from peers import dlt  # noqa: E402 - this folder is not a package
from protocol import MIN_CONFIDENCE, load_detections  # noqa: E402

from torchmocap.cameras import CameraRig, bundle_adjust, report_markdown  # noqa: E402
from torchmocap.evaluation import leave_one_camera_out  # noqa: E402

RECORDING = HERE.parents[2] / "shared" / "data" / "multiview" / "pose2sim_balancing"
RESULTS = HERE / "results"
#: (refined frames, scored frames)
SPLITS = (((0, 60), (60, 100)), ((40, 100), (0, 40)))
#: the refined groups compared
GROUPS = (("rotation", "translation"), ("rotation", "translation", "focal"),
          ("rotation", "translation", "focal", "time_offset"),
          ("rotation", "translation", "focal", "principal_point", "distortion", "time_offset"))


def heldout_medians(points: torch.Tensor, rig: CameraRig) -> list[float]:
    """Leave-one-camera-out median px per camera of detections ``(T, C, K, 3)``."""
    scores = leave_one_camera_out(points, rig, MIN_CONFIDENCE, triangulate=dlt)
    return [float(s.median_px) for s in scores]


def run_split(det, train: tuple[int, int], test: tuple[int, int], groups: tuple[str, ...]
              ) -> dict:
    t0 = time.perf_counter()
    res = bundle_adjust(det.points, det.rig, groups=groups, frames=train, fps=det.fps)
    seconds = time.perf_counter() - t0
    scored = det.points[test[0]:test[1]]
    before = heldout_medians(scored, det.rig)
    after = heldout_medians(scored, res.rig.double())
    report = res.report()
    rig = res.rig.double()
    return {"refined_frames": list(train), "scored_frames": list(test), "groups": list(groups),
            "rig": {"R": rig.R.tolist(), "centres": rig.camera_centers().tolist(),
                    "focal": rig.K[:, 0, 0].tolist()},
            "heldout_median_px_before": before, "heldout_median_px_after": after,
            "mean_before": sum(before) / len(before), "mean_after": sum(after) / len(after),
            "seconds": seconds, "report": report, "report_markdown": report_markdown(report)}


def _row(name: str, values: list[float]) -> str:
    mean = sum(values) / len(values)
    return f"| {name} | " + " | ".join(f"{v:.1f}" for v in values) + f" | **{mean:.1f}** |"


def agreement(a: dict, b: dict) -> list[dict]:
    """Per camera, how far two refinements (of the same groups on different frames) are
    apart, against their standard deviations (``z`` = difference / combined std)."""
    from torchmocap.geometry import geodesic_angle

    out = []
    for c, (ea, eb) in enumerate(zip(a["report"]["cameras"], b["report"]["cameras"])):
        Ra, Rb = (torch.tensor(r["rig"]["R"][c], dtype=torch.float64) for r in (a, b))
        ca, cb = (torch.tensor(r["rig"]["centres"][c], dtype=torch.float64) for r in (a, b))
        df = ea["focal_change_percent"] - eb["focal_change_percent"]
        sf = math.hypot(ea["focal_std_percent"], eb["focal_std_percent"])
        dr = math.degrees(float(geodesic_angle(Ra, Rb)))
        sr = math.hypot(ea["rotation_change_std_deg"], eb["rotation_change_std_deg"])
        dc = 1000 * float((ca - cb).norm())
        sc = math.hypot(ea["centre_change_std_mm"], eb["centre_change_std_mm"])
        out.append({"name": ea["name"], "focal_a": ea["focal_change_percent"],
                    "focal_b": eb["focal_change_percent"], "focal_z": abs(df) / sf,
                    "rotation_deg": dr, "rotation_z": dr / sr, "centre_mm": dc,
                    "centre_z": dc / sc, "focal_depth_correlation": (
                        ea["focal_depth_correlation"], eb["focal_depth_correlation"])})
    return out


def agreement_table(a: dict, b: dict) -> list[str]:
    lines = ["| camera | focal % (first) | focal % (second) | z | rotation apart ° | z | "
             "centre apart mm | z | focal–distance correlation |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for e in agreement(a, b):
        rho = ", ".join(f"{r:+.2f}" for r in e["focal_depth_correlation"])
        lines.append(f"| {e['name']} | {e['focal_a']:+.2f} | {e['focal_b']:+.2f} | "
                     f"{e['focal_z']:.1f} | {e['rotation_deg']:.2f} | {e['rotation_z']:.1f} | "
                     f"{e['centre_mm']:.0f} | {e['centre_z']:.1f} | {rho} |")
    return lines


def markdown(runs: list[dict], cameras: list[str], recording: Path, command: str) -> str:
    lines = [
        "# pose2sim_balancing — refining the calibration from the subject (no board)", "",
        f"Recording `{recording.name}`, cameras {', '.join(cameras)}; associated BODY_25B "
        "detections. Each refinement (`torchmocap.cameras.bundle_adjust`: 3D points free per "
        "frame and keypoint from their DLT, Cauchy loss 20 px, detections of confidence > 0.3 "
        "weighted by confidence, default priors 5° / 0.25 m / 5 % focal / 20 px principal point "
        "/ 0.05 k1 k2 / 2 frames, mean gauge; with time offsets a 50 m/s² acceleration prior on "
        "the trajectories) sees all four cameras on its refined frames; the "
        "held-out score is then measured on the *other* frames: each camera left out in turn, "
        "the other three views' detections of confidence > 0.3 triangulated by confidence-"
        "weighted DLT, projected into it and compared with its detections of confidence > 0.3 "
        "(median px, full-resolution pixels). With time offsets refined the score uses the "
        "refined rig alone (each frame triangulated at its own time).", "",
        f"Command: `{command}`", ""]
    for run in runs:
        tr, te = run["refined_frames"], run["scored_frames"]
        lines += [f"## Refined on frames {tr[0]}–{tr[1] - 1}, scored on {te[0]}–{te[1] - 1}: "
                  f"{', '.join(run['groups'])}", "",
                  "| held-out median px | " + " | ".join(cameras) + " | mean |",
                  "|---|" + "---:|" * (len(cameras) + 1),
                  _row("given calibration", run["heldout_median_px_before"]),
                  _row("refined", run["heldout_median_px_after"]), "",
                  f"Refinement: {run['seconds']:.1f} s.", "",
                  "What changed (refined frames; ± one standard deviation):", "",
                  run["report_markdown"], ""]
    summary = ["## Summary: mean held-out median px", "",
               "| refined groups | refined on | scored on | given | refined |",
               "|---|---|---|---:|---:|"]
    for run in runs:
        tr, te = run["refined_frames"], run["scored_frames"]
        summary.append(f"| {', '.join(run['groups'])} | {tr[0]}–{tr[1] - 1} | "
                       f"{te[0]}–{te[1] - 1} | {run['mean_before']:.1f} | "
                       f"{run['mean_after']:.1f} |")
    lines[lines.index(f"Command: `{command}`") + 2:
          lines.index(f"Command: `{command}`") + 2] = summary + [""]
    by_groups: dict[tuple, list[dict]] = {}
    for run in runs:
        by_groups.setdefault(tuple(run["groups"]), []).append(run)
    for groups, pair in by_groups.items():
        if len(pair) != 2 or "focal" not in groups:
            continue
        a, b = pair
        lines += [f"## Do the two splits agree? {', '.join(groups)}", "",
                  f"First: refined on frames {a['refined_frames'][0]}–"
                  f"{a['refined_frames'][1] - 1}; second: {b['refined_frames'][0]}–"
                  f"{b['refined_frames'][1] - 1}. `z`: the difference over the two "
                  "refinements' combined standard deviation (independent splits would give "
                  "|z| of about 1).", ""] + agreement_table(a, b) + [""]
    lines += ["## Notes", "",
              "- The uncertainties are Gauss–Newton standard deviations at the solution, with "
              "the detections' noise σ measured from the residuals; OpenPose's errors are "
              "correlated over frames (a keypoint's offset from the joint persists), which the "
              "model does not know, so they are lower bounds: two splits that disagree by more "
              "say so.",
              "- `not determined` lists parameters whose posterior std exceeds half their prior "
              "width (the prior, not the subject, held them).", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recording", type=Path, default=RECORDING)
    ap.add_argument("--splits", default=None,
                    help="'a:b/c:d,e:f/g:h': refine on a..b-1, score on c..d-1, ...")
    ap.add_argument("--groups", action="append", default=None,
                    help="comma-separated refined groups (repeatable)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    splits = SPLITS if args.splits is None else tuple(
        tuple(tuple(int(v) for v in part.split(":")) for part in s.split("/"))
        for s in args.splits.split(","))
    groups = GROUPS if args.groups is None else tuple(tuple(g.split(",")) for g in args.groups)
    det = load_detections(args.recording)
    runs = []
    for train, test in splits:
        for g in groups:
            run = run_split(det, train, test, g)
            runs.append(run)
            print(f"refined {train}, scored {test}, {','.join(g)}: mean held-out median "
                  f"{run['mean_before']:.1f} -> {run['mean_after']:.1f} px "
                  f"({run['seconds']:.1f} s)")
    command = "OMP_NUM_THREADS=1 python experiments/real_multiview/calibration_refinement.py" + (
        "" if argv is None or not argv else " " + " ".join(argv))
    from torchmocap.atomic import atomic_path

    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out / "calibration_refinement.md") as tmp:
        tmp.write_text(markdown(runs, det.cameras, args.recording, command))
    data = {"recording": str(args.recording.name), "cameras": det.cameras, "command": command,
            "machine": {"python": platform.python_version(), "torch": torch.__version__},
            "runs": [{k: v for k, v in r.items() if k != "report_markdown"} for r in runs]}
    with atomic_path(args.out / "calibration_refinement.json") as tmp:
        tmp.write_text(json.dumps(data, indent=1))
    print(f"wrote {args.out / 'calibration_refinement.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
