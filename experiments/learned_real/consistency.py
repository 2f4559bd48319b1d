"""What limits the held-out error: how well the cameras agree with each other.

For every subset of two or more of the recording's cameras, every frame is fitted to that
subset's detections (the hand-set keypoint term, frame-by-frame L-BFGS from the subject's first
pose: :func:`torchmocap.learning.keypoints.track_poses`), and the fit is projected into every
camera: the median pixel error and the mean residual (the shift common to all keypoints) against
that camera's detections of confidence > 0.3, in full-resolution pixels. A camera in the subset
shows the detector's noise around a fit it took part in (a floor: the fit is pulled towards
it); a camera outside it shows what a held-out score can reach from those views. A large mean
residual that appears whenever a camera is left out — and shrinks when it takes part — is a
disagreement of that camera with the others (calibration or a detector's habit in that view),
which no term trained without that camera can see.

Writes ``results/consistency.md`` and ``results/consistency.json``.

Usage (from the repository root)::

    OMP_NUM_THREADS=1 python experiments/learned_real/consistency.py
"""

from __future__ import annotations

import argparse
import itertools
import json
import warnings
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
RECORDING = HERE.parents[2] / "shared" / "data" / "multiview" / "pose2sim_balancing"
MIN_CONFIDENCE = 0.3


def main(argv: list[str] | None = None) -> int:
    from torchmocap.assembly import Runtime
    from torchmocap.data.recordings.loader import load_recording
    from torchmocap.filters.tracking.tracker import start_pose
    from torchmocap.learning.keypoints import stack_detections, track_poses
    from torchmocap.likelihoods import LearnedKeypointLikelihood, Poses

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recording", type=Path, default=RECORDING)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*codec's crop")
        seq = load_recording(args.recording, scale=args.scale, masks="none")
    rt = Runtime.from_sequence(seq)
    sk = rt.skeleton
    theta0 = start_pose(seq).to(sk.offsets.dtype)

    def term(s):
        return LearnedKeypointLikelihood(s.rig, sk, s.joint_names, rt.keypoint_map,
                                         min_confidence=0.1)

    every = term(seq)
    det = stack_detections(every, seq)
    names = list(seq.rig.names)
    C = len(names)
    rows = []
    for r in range(2, C + 1):
        for sub in itertools.combinations(range(C), r):
            s = seq.select_cameras(list(sub))
            t = term(s)
            theta = track_poses(t, sk, stack_detections(t, s), theta0, 30)
            with torch.no_grad():
                pix = every.project(t.keypoints(Poses(theta, sk)))  # (T, C, K', 2)
            views = {}
            for c in range(C):
                ok = det.conf[:, c] > MIN_CONFIDENCE
                res = (pix[:, c] - det.uv[:, c])[ok] / args.scale
                views[names[c]] = {"in_fit": c in sub,
                                   "median_px": round(float(res.norm(dim=-1).median()), 1),
                                   "mean_residual_px": [round(float(v), 1) for v in res.mean(0)],
                                   "median_px_about_mean": round(float(
                                       (res - res.mean(0)).norm(dim=-1).median()), 1)}
            rows.append({"cameras": [names[i] for i in sub], "views": views})
            print(rows[-1]["cameras"], {n: v["median_px"] for n, v in views.items()}, flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "consistency.json").write_text(json.dumps(rows, indent=1))
    head = "| fitted to | " + " | ".join(names) + " |\n|---|" + "---:|" * C + "\n"
    body = ""
    for row in rows:
        cells = []
        for n in names:
            v = row["views"][n]
            m = v["mean_residual_px"]
            cell = f"{v['median_px']:.1f} ({m[0]:+.0f}, {m[1]:+.0f})"
            cells.append(f"**{cell}**" if v["in_fit"] else cell)
        body += f"| {', '.join(row['cameras'])} | " + " | ".join(cells) + " |\n"
    note = ("\nEach cell: median error in full-resolution px (the mean residual u, v in "
            "parentheses) of the fit to the listed cameras, in that column's camera; bold: the "
            "camera took part in the fit.\n")
    (args.out / "consistency.md").write_text(head + body + note)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
