"""Smoother variants on the same filtered tracks: the default (3-axis joints on SO(3), one ML
noise pair per group), every rotation DoF as an angle, one noise pair per DoF, and a fixed
5-frame moving average of the angles (weights 1-2-3-2-1) as the simple peer.

Reads every run of the smoothing sweep (``runs/kalman/**/track.npz``: the tracker's own
estimates ``theta_filtered``; the runs' ``.hydra/config.yaml`` rebuild each sequence for the
subject's skeleton and truth) and writes ``results/variants.md``::

    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=smoothing/kalman hydra/launcher=joblib
    python experiments/smoothing/variants.py

MPJPE (mm) over frames 1..T-1, mean over the runs of each scenario and tracker.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
VARIANTS = ("filtered", "kalman (default)", "kalman, angles", "kalman, per DoF",
            "moving average 1-2-3-2-1")


def moving_average(theta: torch.Tensor, weights=(1, 2, 3, 2, 1)) -> torch.Tensor:
    """Centred weighted moving average of ``theta (T, D)`` (ends padded with the end values,
    rotation DoFs unwrapped first); frame 0 kept."""
    from torchmocap.filters.smoothing import unwrap_angles

    k = torch.tensor(weights, dtype=theta.dtype)
    k = k / k.sum()
    h = len(weights) // 2
    u = unwrap_angles(theta)
    p = torch.cat([u[:1].expand(h, -1), u, u[-1:].expand(h, -1)])
    out = sum(k[i] * p[i:i + len(u)] for i in range(len(weights)))
    out[0] = theta[0]
    return out


def evaluate(run: Path) -> dict:
    from omegaconf import OmegaConf

    from torchmocap.assembly import load_sequence
    from torchmocap.filters import KalmanSmoother

    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    seq = load_sequence(cfg)
    sk = seq.ground_truth.build_skeleton().double()
    truth = seq.ground_truth.positions[1:].double()
    filt = torch.as_tensor(np.load(run / "track.npz")["theta_filtered"], dtype=torch.float64)

    def mpjpe(theta):
        return float((sk(theta[1:]).positions - truth).norm(dim=-1).mean()) * 1000

    return {"filtered": mpjpe(filt),
            "kalman (default)": mpjpe(KalmanSmoother(skeleton=sk).smooth_theta(filt)[0]),
            "kalman, angles": mpjpe(KalmanSmoother(skeleton=sk, rotations="angles")
                                    .smooth_theta(filt)[0]),
            "kalman, per DoF": mpjpe(KalmanSmoother(skeleton=sk, per_dof=True)
                                     .smooth_theta(filt)[0]),
            "moving average 1-2-3-2-1": mpjpe(sk.clamp(moving_average(filt)))}


def group_runs(runs_dir: Path, evaluate, script: str) -> dict | None:
    """``{(scenario, tracker): [evaluate(run), ...]}`` over the runs of a smoothing sweep
    (``<scenario>/<clip>/<tracker>/seed<s>/track.npz``); ``None`` (and a message naming
    ``script``) when there are none."""
    runs = sorted(p.parent for p in runs_dir.glob("*/*/*/seed*/track.npz"))
    if not runs:
        print(f"{script}: no track.npz under {runs_dir} (run the sweep first)", file=sys.stderr)
        return None
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in runs:
        groups.setdefault((r.parts[-4], r.parts[-2]), []).append(evaluate(r))
    return groups


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, default=HERE / "runs" / "kalman")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    groups = group_runs(args.runs, evaluate, "variants")
    if groups is None:
        return 2
    lines = ["# Smoother variants on the same filtered tracks", "",
             "MPJPE (mm), frames 1..T-1, mean over the runs (clips) of each scenario and "
             "tracker; `experiments/smoothing/variants.py`.", "",
             "| scenario | tracker | runs | " + " | ".join(VARIANTS) + " |",
             "|---|---|---:|" + "---:|" * len(VARIANTS)]
    for (s, t), rows in sorted(groups.items()):
        cells = [f"{np.mean([r[v] for r in rows]):.1f}" for v in VARIANTS]
        lines.append(f"| {s} | `{t}` | {len(rows)} | " + " | ".join(cells) + " |")
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = args.out / "variants.md.tmp"
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(args.out / "variants.md")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
