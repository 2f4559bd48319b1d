"""Fixed-lag smoothing: what a tracker that reports each frame ``L`` frames late gains.

The Kalman smoother with ``lag=L`` estimates frame ``t`` from the tracker's estimates up to
``t + L`` only (``L = 0``: the Kalman filter of the estimates, causal; no lag: the whole clip).
Reads every run of a smoothing sweep (``track.npz``: the tracker's own estimates
``theta_filtered``; the runs' ``.hydra/config.yaml`` rebuild each sequence for the subject's
skeleton and truth), smooths the same filtered track with every lag and writes
``results/lag.md``::

    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=smoothing/kalman hydra/launcher=joblib \
        hydra.sweep.dir=experiments/smoothing/runs/lag
    python experiments/smoothing/lag.py

MPJPE (mm) and validation orientation error (deg) over frames 1..T-1, mean over the runs
(clips) of each scenario and tracker. The noise is fitted on the whole track for every lag.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
LAGS = (0, 1, 2, 5, None)


def evaluate(run: Path, lags=LAGS) -> dict:
    """``{column: (mpjpe mm, orientation deg)}`` of one run: the filtered track and every lag."""
    from omegaconf import OmegaConf

    from torchmocap.assembly import load_sequence
    from torchmocap.evaluation import track_errors
    from torchmocap.filters import KalmanSmoother

    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    seq = load_sequence(cfg)
    sk = seq.ground_truth.build_skeleton()
    filt = torch.as_tensor(np.load(run / "track.npz")["theta_filtered"], dtype=torch.float32)

    def errors(theta):
        e = track_errors(seq, sk, theta)["summary"]
        return e["mpjpe_mm"]["mean"], e["orientation_error_deg"]["mean"]

    out = {"filtered": errors(filt)}
    for lag in lags:
        out[column(lag)] = errors(KalmanSmoother(skeleton=sk, lag=lag).smooth_theta(filt)[0])
    return out


def column(lag) -> str:
    return "whole clip" if lag is None else f"lag {lag}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, default=HERE / "runs" / "lag")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    from variants import group_runs  # this directory's sibling script

    groups = group_runs(args.runs, evaluate, "lag")
    if groups is None:
        return 2
    cols = ["filtered"] + [column(lag) for lag in LAGS]
    lines = ["# Fixed-lag smoothing of the same filtered tracks", "",
             "MPJPE (mm) / validation orientation error (deg), frames 1..T-1, mean over the runs "
             "(clips) of each scenario and tracker; lag L: frame t from the estimates up to "
             "t + L (25 fps: 40 ms per frame of delay); `experiments/smoothing/lag.py`.", "",
             "| scenario | tracker | runs | " + " | ".join(cols) + " |",
             "|---|---|---:|" + "---:|" * len(cols)]
    for (s, t), rows in sorted(groups.items()):
        cells = [f"{np.mean([r[c][0] for r in rows]):.1f} / {np.mean([r[c][1] for r in rows]):.2f}"
                 for c in cols]
        lines.append(f"| {s} | `{t}` | {len(rows)} | " + " | ".join(cells) + " |")
    from torchmocap.atomic import atomic_path

    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out / "lag.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    plot(groups, args.out / "lag.png")
    print("\n".join(lines))
    return 0


def plot(groups: dict, path: Path) -> None:
    """MPJPE against the lag per scenario and tracker (the whole clip at the right end, the
    filtered estimates dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchmocap.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(6, 3.6))
    xs = list(range(len(LAGS)))
    for (s, t), rows in sorted(groups.items()):
        ys = [np.mean([r[column(lag)][0] for r in rows]) for lag in LAGS]
        line, = ax.plot(xs, ys, marker="o", label=f"{t}, {s}")
        ax.axhline(np.mean([r["filtered"][0] for r in rows]), ls="--", lw=0.8,
                   color=line.get_color())
    ax.set_xticks(xs, [str(lag) if lag is not None else "whole\nclip" for lag in LAGS])
    ax.set_xlabel("lag (frames at 25 fps); dashed: the tracker's own estimates")
    ax.set_ylabel("MPJPE (mm)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
