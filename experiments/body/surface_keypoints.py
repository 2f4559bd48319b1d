"""Keypoints from the surface on the real recording: the keypoint map's hand-placed offsets
against the points of the subject's fitted Anny body, each camera of ``pose2sim_balancing``
held out in turn.

Split a of ``experiments/real_multiview`` (the calibration refined from the subject on frames
0–59, tracked and scored on 60–99), ``tracker=real_local`` with the Anny body fitted at the first
frame (``+body_fit@tracker.body_fit=anny``), keypoints from the map
(``tracker.likelihood.terms.keypoints.surface_keypoints=false``) or from the fitted body's surface
(``...=true``) with either anchor (``surface_anchor``: ``joint``, the points where the body puts
them; ``map``, the body shapes each joint's group, the map places it). From the repository
root::

    export OMP_NUM_THREADS=1
    K=tracker.likelihood.terms.keypoints
    for cam in cam01 cam02 cam03 cam04; do
      for v in "map $K.surface_keypoints=false" \\
               "surface_joint $K.surface_keypoints=true $K.surface_anchor=joint" \\
               "surface_map $K.surface_keypoints=true $K.surface_anchor=map"; do
        set -- $v; name=$1; shift
        torchmocap-track data=recording data.path=../shared/data/multiview/pose2sim_balancing \\
          data.start=60 data.stop=100 data.calibration.refine=true \\
          'data.calibration.frames=[0,60]' tracker=real_local +body_fit@tracker.body_fit=anny \\
          "$@" evaluation.heldout_camera=$cam threads=1 overlays=0 glb.enabled=false \\
          progress=false hydra.run.dir=experiments/body/runs/surface_keypoints/$name/$cam
      done
    done
    python experiments/body/surface_keypoints.py

Each run's track is scored in its held-out view's OpenPose detections through the refined rig,
with the keypoints the run itself tracked (``metrics.json`` ``heldout.keypoint_mapping``): over
all keypoints, over the keypoints the surface places (nose, eyes, ears, head top, heels, toes)
and over the others. Writes ``results/surface_keypoints.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
REAL = HERE.parent / "real_multiview"
if str(REAL) not in sys.path:
    sys.path.insert(0, str(REAL))

from protocol import KEYPOINTS, load_detections  # noqa: E402
from self_calibration_keypoints import pixel_errors  # noqa: E402
from self_calibration_report import RECORDING, SPLITS, refined_rig  # noqa: E402

from torchmocap.atomic import write_text_atomic  # noqa: E402
from torchmocap.body.surface_keypoints import KEYPOINT_POINTS  # noqa: E402

VARIANTS = (("map", "keypoint map"), ("surface_joint", "surface, anchor=joint"),
            ("surface_map", "surface, anchor=map"))
SURFACE = [k for k in KEYPOINTS if k in KEYPOINT_POINTS]


def tracked_keypoints(run: Path) -> torch.Tensor:
    """``(T, K, 3)`` the run's BODY_25B keypoints with the offsets it tracked with."""
    from torchmocap.io import read_bvh
    from torchmocap.skeleton import keypoint_positions, load_keypoint_map

    m = json.loads((run / "metrics.json").read_text())
    mapping = m["heldout"]["keypoint_mapping"]
    clip = read_bvh(run / "tracked.bvh")
    km = load_keypoint_map("body_25b", clip.to_skeleton()[0])
    off = torch.tensor([mapping[n]["offset"] for n in km.names], dtype=torch.float64)
    x = keypoint_positions(clip.global_positions(), clip.global_rotations(), km, off)
    out = torch.full((x.shape[0], len(KEYPOINTS), 3), float("nan"), dtype=torch.float64)
    out[:, km.columns(KEYPOINTS)] = x.double()
    return out


def _median(e: torch.Tensor, names) -> float:
    return float(e[:, [KEYPOINTS.index(n) for n in names]].nanmedian())


def rows_of(runs: Path) -> dict:
    full = load_detections(RECORDING)
    rig, _ = refined_rig(full, SPLITS["a"][0])
    det = dataclasses.replace(load_detections(RECORDING, *SPLITS["a"][1]), rig=rig)
    others = [k for k in KEYPOINTS if k not in KEYPOINT_POINTS]
    out = {}
    for v, _ in VARIANTS:
        for c, cam in enumerate(det.cameras):
            run = runs / v / cam
            if not (run / "metrics.json").is_file():
                continue
            m = json.loads((run / "metrics.json").read_text())
            e = pixel_errors(tracked_keypoints(run), det, c)
            per = {n: float(e[:, KEYPOINTS.index(n)].nanmedian()) for n in SURFACE}
            out[v, cam] = {"median_px": _median(e, KEYPOINTS), "surface_px": _median(e, SURFACE),
                           "others_px": _median(e, others), "per_keypoint": per,
                           "reported_px": m["heldout"]["median_px"],
                           "iou": m["heldout"].get("silhouette_iou"),
                           "seconds_per_frame": m["seconds_per_frame"]}
    return out


def report(rows: dict) -> str:
    cams = sorted({c for _, c in rows})
    f = lambda x: "–" if x is None or x != x else f"{x:.1f}"  # noqa: E731
    lines = ["# Keypoints from the surface on pose2sim_balancing", "",
             "Split a (calibration refined on 0–59, tracked and scored on 60–99), "
             "`real_local` + the Anny body fit, each camera held out; median px in the held-out "
             "view (full-resolution pixels, detections of confidence > 0.3). "
             "`python experiments/body/surface_keypoints.py` (commands in its docstring).", "",
             "| held out | keypoints | all | surface keypoints (nose, eyes, ears, head top, "
             "heels, toes) | the others | IoU | s/frame |", "|---|---|---:|---:|---:|---:|---:|"]
    for cam in cams:
        for v, label in VARIANTS:
            r = rows.get((v, cam))
            if r is not None:
                lines.append(f"| {cam} | {label} | {f(r['median_px'])} | {f(r['surface_px'])} | "
                             f"{f(r['others_px'])} | {r['iou']:.3f} | "
                             f"{r['seconds_per_frame']:.2f} |")
    for v, label in VARIANTS:
        rs = [rows[v, c] for c in cams if (v, c) in rows]
        if rs:
            mean = lambda k, rs=rs: sum(r[k] for r in rs) / len(rs)  # noqa: E731
            lines.append(f"| **mean** | {label} | **{f(mean('median_px'))}** | "
                         f"{f(mean('surface_px'))} | {f(mean('others_px'))} | "
                         f"{mean('iou'):.3f} | {mean('seconds_per_frame'):.2f} |")
    lines += ["", "Per surface keypoint (median px, mean over the held-out cameras; " +
              " / ".join(label for _, label in VARIANTS) + "):", ""]
    cells = []
    for n in SURFACE:
        vals = {v: [rows[v, c]["per_keypoint"][n] for c in cams if (v, c) in rows
                    and rows[v, c]["per_keypoint"][n] == rows[v, c]["per_keypoint"][n]]
                for v, _ in VARIANTS}
        if all(vals.values()):
            cells.append(f"{n} " + " / ".join(f"{sum(vals[v]) / len(vals[v]):.1f}"
                                                for v, _ in VARIANTS))
    lines += ["; ".join(cells) + ".", ""]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=HERE / "runs" / "surface_keypoints")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    rows = rows_of(args.runs)
    if not rows:
        raise SystemExit(f"no runs under {args.runs}")
    text = report(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "surface_keypoints.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
