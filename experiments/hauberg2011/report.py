"""Hauberg & Pedersen (2011): tables and plots of the importance-distribution sweeps (Figs. 6 and 8)
and of the rejection-sampling "failed experiment" (Fig. 3) from the runs' ``metrics.json``.

The runs are made by the experiment configs (from the repository root)::

    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=hauberg2011/importance \
        hydra/launcher=joblib
    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=hauberg2011/rejection \
        hydra/launcher=joblib
    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=hauberg2011/heldout \
        hydra/launcher=joblib
    python experiments/hauberg2011/report.py importance   # -> results/importance.md, .png
    python experiments/hauberg2011/report.py heldout      # -> results/heldout.md, .png
    python experiments/hauberg2011/report.py rejection    # -> results/rejection.md, .png

Each job writes ``runs/<sweep>/<clip>/<tracker>/n<particles>/seed<s>/metrics.json``. Per clip,
tracker and particle count the tables give the tracking error of eq. 16 (mean distance of the skin
markers to the estimated capsule skin, mm; mean over frames, then mean ± std over seeds), the
effective sample size (eq. 17, time average), seconds per frame and, for the data-driven
proposals, the ratios of ESS and time to the angular prior's at the same particle count (the
paper's ×1.6–2.2 / ×2.3–3.3 ESS at about +10 % time). ``--runs`` and ``--out`` point elsewhere.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
CLIPS = {"swim": "arm waving (CMU swim)", "grab_high": "arbitrary arm motion (HDM05 grab high)",
         "basketball": "held out: throwing a basketball (HDM05 bd)",
         "boxing": "held out: boxing (CMU21 box)"}
SWEEPS = {
    "importance": {
        "trackers": {"hauberg_angular": "angular prior (eq. 3)",
                     "hauberg_spatial": "spatial prior (eq. 6)",
                     "hauberg_silhouette": "silhouette-driven (eq. 12)",
                     "hauberg_depth": "depth-driven (eq. 14)"},
        "clips": ["swim", "grab_high"],
        "particles": [25, 50, 100, 200],
    },
    "heldout": {
        "trackers": {"hauberg_angular": "angular prior (eq. 3)",
                     "hauberg_spatial": "spatial prior (eq. 6)",
                     "hauberg_silhouette": "silhouette-driven (eq. 12)",
                     "hauberg_depth": "depth-driven (eq. 14)"},
        "clips": ["basketball", "boxing"],
        "particles": [100, 200],
    },
    "rejection": {
        "trackers": {"hauberg_angular": "angular prior (eq. 3)",
                     "hauberg_rejection": "rejection-sampled (eq. 4)"},
        "clips": ["swim"],
        "particles": [25, 50, 100],
    },
}
SEEDS = [0, 1, 2]


def _mean_sd(vals: list[float]) -> tuple[float, float]:
    n = len(vals)
    m = sum(vals) / n
    return m, (math.sqrt(sum((v - m) ** 2 for v in vals) / (n - 1)) if n > 1 else 0.0)


def load(runs: Path, spec: dict) -> tuple[dict, list[str]]:
    """``{(clip, tracker, n): [metrics, ...]}`` and the missing / failed run directories."""
    out, missing = {}, []
    for c in spec["clips"]:
        for t in spec["trackers"]:
            for n in spec["particles"]:
                for s in SEEDS:
                    d = runs / c / t / f"n{n}" / f"seed{s}"
                    p = d / "metrics.json"
                    if p.is_file():
                        out.setdefault((c, t, n), []).append(json.loads(p.read_text()))
                    else:
                        why = " (failed)" if (d / "failure.json").is_file() else ""
                        missing.append(f"{d.relative_to(runs)}{why}")
    return out, missing


def summarise(runs: dict) -> dict:
    """Per cell: mean and seed spread of marker error (mm), ESS, s/frame, rejections/sample."""
    table = {}
    for key, ms in runs.items():
        row = {"seeds": len(ms)}
        row["error"] = _mean_sd([m["marker_error_mm"]["mean"] for m in ms])
        row["mpjpe"] = _mean_sd([m["mpjpe_mm"]["mean"] for m in ms])
        ess = [m["ess_mean"] for m in ms if "ess_mean" in m]
        row["ess"] = _mean_sd(ess) if ess else None
        row["time"] = _mean_sd([m["seconds_per_frame"] for m in ms])
        rej = [m["proposal_mean"]["rejections_per_sample"] for m in ms
               if "rejections_per_sample" in m.get("proposal_mean", {})]
        row["rejections"] = _mean_sd(rej) if rej else None
        fb = [sum(v for k, v in m.get("proposal_mean", {}).items() if k.startswith("fallback_"))
              for m in ms]
        row["fallback"] = sum(fb) / len(fb)
        table[key] = row
    return table


def _cell(v, fmt="{:.1f}") -> str:
    if v is None:
        return "–"
    m, sd = v
    return f"{fmt.format(m)} ± {fmt.format(sd)}"


def markdown(sweep: str, spec: dict, table: dict, missing: list[str]) -> str:
    lines = [f"# Hauberg & Pedersen (2011): {sweep} sweep", ""]
    base = "hauberg_angular"
    for c in spec["clips"]:
        if not any(k[0] == c for k in table):
            continue
        lines += [f"## {CLIPS.get(c, c)}", "",
                  "| proposal | particles | error eq. 16 (mm) | MPJPE (mm) | ESS | ESS / angular "
                  "| s/frame | time / angular | rejections / sample |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for t, name in spec["trackers"].items():
            for n in spec["particles"]:
                row = table.get((c, t, n))
                if row is None:
                    continue
                ref = table.get((c, base, n))
                ess_ratio = time_ratio = "–"
                if ref is not None and t != base:
                    if row["ess"] and ref["ess"]:
                        ess_ratio = f"×{row['ess'][0] / ref['ess'][0]:.2f}"
                    time_ratio = f"×{row['time'][0] / ref['time'][0]:.2f}"
                lines.append(f"| {name} | {n} | {_cell(row['error'])} | {_cell(row['mpjpe'])} "
                             f"| {_cell(row['ess'])} | {ess_ratio} | "
                             f"{_cell(row['time'], '{:.2f}')} | {time_ratio} | "
                             f"{_cell(row['rejections'], '{:.0f}')} |")
        lines.append("")
    lines.append("Cells: mean over frames, then mean ± std over tracker seeds "
                 f"{SEEDS[0]}–{SEEDS[-1]}.")
    if missing:
        lines += ["", f"Missing runs ({len(missing)}): " + ", ".join(missing[:20])
                  + (" …" if len(missing) > 20 else "")]
    return "\n".join(lines) + "\n"


def plot(sweep: str, spec: dict, table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    third = "rejections" if sweep == "rejection" else "ess"
    panels = [("error", "error eq. 16 (mm)"),
              (third, "rejections per sample" if third == "rejections" else "ESS"),
              ("time", "seconds per frame")]
    clips = [c for c in spec["clips"] if any(k[0] == c for k in table)]
    fig, axes = plt.subplots(len(clips), 3, figsize=(13, 3.6 * len(clips)), squeeze=False)
    for i, c in enumerate(clips):
        for j, (key, label) in enumerate(panels):
            ax = axes[i, j]
            for t, name in spec["trackers"].items():
                ns = [n for n in spec["particles"] if (c, t, n) in table
                      and table[(c, t, n)][key] is not None]
                if not ns:
                    continue
                m = [table[(c, t, n)][key][0] for n in ns]
                sd = [table[(c, t, n)][key][1] for n in ns]
                ax.errorbar(ns, m, yerr=sd, marker="o", capsize=3, label=name)
            ax.set_xscale("log")
            ax.minorticks_off()
            ax.set_xticks(spec["particles"])
            ax.set_xticklabels([str(n) for n in spec["particles"]])
            ax.set_xlabel("particles")
            ax.set_ylabel(label)
            ax.set_title(CLIPS.get(c, c), fontsize=9)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sweep", choices=sorted(SWEEPS))
    ap.add_argument("--runs", type=Path, default=None,
                    help="the sweep's run directory (default runs/<sweep>)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--particles", type=int, nargs="+", default=None,
                    help="particle counts to tabulate (default: the sweep's own)")
    args = ap.parse_args(argv)
    spec = dict(SWEEPS[args.sweep])
    if args.particles:
        spec["particles"] = sorted(set(args.particles))
    runs_dir = args.runs or HERE / "runs" / args.sweep
    runs, missing = load(runs_dir, spec)
    if not runs:
        print(f"report: no metrics.json under {runs_dir}", file=sys.stderr)
        return 2
    table = summarise(runs)
    args.out.mkdir(parents=True, exist_ok=True)
    md = markdown(args.sweep, spec, table, missing)
    tmp = args.out / f"{args.sweep}.md.tmp"
    tmp.write_text(md)
    tmp.replace(args.out / f"{args.sweep}.md")
    plot(args.sweep, spec, table, args.out / f"{args.sweep}.png")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
