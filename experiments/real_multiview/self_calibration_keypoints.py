"""Where ``real_local`` and the weighted DLT differ, keypoint by keypoint, on the refined rig.

For each split of ``self_calibration_report.py`` and each held-out camera: the held-out median
px of the ``real_local`` run (``runs_selfcal/<split>/refined/real_local/<cam>``) and of the
weighted DLT from the other three views, over all keypoints, without the head keypoints (nose,
eyes, ears, neck: placed by the keypoint map's fixed offsets on the head and neck), over the
two ears alone, per ten-frame block, and the six keypoints where the track is furthest behind.
Writes ``results/self_calibration_keypoints.md``. Command (from the repository root, after
``self_calibration.sh``)::

    OMP_NUM_THREADS=1 python experiments/real_multiview/self_calibration_keypoints.py
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from peers import dlt  # noqa: E402
from protocol import KEYPOINTS, MIN_CONFIDENCE, load_detections  # noqa: E402
from report import track_keypoints  # noqa: E402
from self_calibration_report import RECORDING, RESULTS, RUNS, SPLITS, refined_rig  # noqa: E402

from torchmocap.atomic import write_text_atomic  # noqa: E402

HEAD = ("Nose", "LEye", "REye", "LEar", "REar", "Neck")
EARS = ("LEar", "REar")


def pixel_errors(points: torch.Tensor, det, camera: int) -> torch.Tensor:
    """``(T, K)`` pixel distances of ``points (T, K, 3)`` to camera ``camera``'s confident
    detections (NaN elsewhere)."""
    uv = det.rig.subset([camera]).project(points.double())[0][..., 0, :, :]
    obs = det.points[:, camera]
    e = (uv - obs[..., :2]).norm(dim=-1)
    return torch.where(obs[..., 2] > MIN_CONFIDENCE, e, torch.full_like(e, float("nan")))


def _median(e: torch.Tensor, names=None, exclude=False) -> float:
    cols = list(range(len(KEYPOINTS)))
    if names is not None:
        pick = [KEYPOINTS.index(n) for n in names]
        cols = [k for k in cols if (k in pick) != exclude]
    return float(e[:, cols].nanmedian())


def rows_of(split: str) -> list[str]:
    full = load_detections(RECORDING)
    rig, _ = refined_rig(full, SPLITS[split][0])
    det = dataclasses.replace(load_detections(RECORDING, *SPLITS[split][1]), rig=rig)
    out = []
    for c, cam in enumerate(det.cameras):
        others = [i for i in range(len(det.cameras)) if i != c]
        sub = det.points[:, others]
        pts = {"track": track_keypoints(RUNS / split / "refined" / "real_local" / cam),
               "dlt": dlt(sub[..., :2], sub[..., 2], det.rig.subset(others))}
        err = {k: pixel_errors(v, det, c) for k, v in pts.items()}
        cell = {k: (_median(e), _median(e, HEAD, exclude=True), _median(e, EARS))
                for k, e in err.items()}
        blocks = {k: [float(e[i:i + 10].nanmedian()) for i in range(0, e.shape[0], 10)]
                  for k, e in err.items()}
        gap = []
        for k, name in enumerate(KEYPOINTS):
            a, b = err["track"][:, k].nanmedian(), err["dlt"][:, k].nanmedian()
            if torch.isfinite(a) and torch.isfinite(b):
                gap.append((float(a - b), name, float(a), float(b)))
        gap.sort(reverse=True)
        worst = ", ".join(f"{n} {a:.1f}/{b:.1f}" for _, n, a, b in gap[:6])
        f = lambda t: " / ".join(f"{x:.1f}" for x in t)  # noqa: E731
        out.append(f"| {split} | {cam} | {f((cell['track'][0], cell['dlt'][0]))} | "
                   f"{f((cell['track'][1], cell['dlt'][1]))} | "
                   f"{f((cell['track'][2], cell['dlt'][2]))} | {f(blocks['track'])} | "
                   f"{f(blocks['dlt'])} | {worst} |")
    return out


def main() -> int:
    lines = ["# Self-calibration: `real_local` against the weighted DLT, keypoint by keypoint", "",
             "Command: `OMP_NUM_THREADS=1 python experiments/real_multiview/"
             "self_calibration_keypoints.py` (after `self_calibration.sh`). Refined rig of each "
             "split; each camera held out on the scored frames; median px of its detections "
             "of confidence > 0.3, track / DLT.", "",
             "| split | held out | all keypoints | without nose, eyes, ears, neck | ears | "
             "track per 10 frames | DLT per 10 frames | furthest behind (track/DLT) |",
             "|---|---|---|---|---|---|---|---|"]
    for split in SPLITS:
        lines += rows_of(split)
    write_text_atomic(RESULTS / "self_calibration_keypoints.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
