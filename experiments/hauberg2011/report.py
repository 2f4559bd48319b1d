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

and the real 4-camera frame (no ground truth; per-view silhouette IoU of the fitted model)::

    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=hauberg2011/bodytrack \
        hydra/launcher=joblib
    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=hauberg2011/bodytrack \
        tracker=real_frame_hull 'tracker.body_fit.offsets=[]' \
        tracker.name=real_frame_hull_centred hydra/launcher=joblib
    python experiments/hauberg2011/report.py bodytrack    # -> results/bodytrack.md, .png

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
# the real frame: runs/bodytrack/<tracker>/seed<s>/metrics.json
BODYTRACK = {"real_frame": "Gaussian diffusion, anthropometric radii (`real_frame`)",
             "real_frame_hull_centred": "limb jumps into the unexplained hull, radii fitted, head "
                                        "on the neck's axis (`real_frame_hull` with "
                                        "`body_fit.offsets=[]`)",
             "real_frame_hull": "limb jumps, radii and the head's offset fitted "
                                "(`real_frame_hull`)"}
IOU_TARGET = 0.80


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


def load_bodytrack(runs: Path) -> tuple[dict, list[str]]:
    """``{tracker: [metrics, ...]}`` of the real-frame fits and the missing run directories."""
    out, missing = {}, []
    for t in BODYTRACK:
        for s in SEEDS:
            d = runs / t / f"seed{s}"
            p = d / "metrics.json"
            if p.is_file():
                out.setdefault(t, []).append(json.loads(p.read_text()))
            else:
                why = " (failed)" if (d / "failure.json").is_file() else ""
                missing.append(f"{d.relative_to(runs)}{why}")
    return out, missing


def summarise_bodytrack(runs: dict) -> dict:
    """Per tracker: per-view IoU (mean over seeds), mean IoU (mean ± sd over seeds, min, max),
    and the fitted head offset (mean, cm)."""
    table = {}
    for t, ms in runs.items():
        views = [m["silhouette_iou"]["per_view"] for m in ms]
        nv = len(views[0])
        if any(len(v) != nv for v in views):
            raise ValueError(f"bodytrack: runs of {t} disagree on the number of views")
        means = [m["silhouette_iou"]["mean"] for m in ms]
        offs = [m["body_fit"]["offsets"]["head_top"] for m in ms
                if "head_top" in (m.get("body_fit") or {}).get("offsets", {})]
        table[t] = {
            "seeds": len(ms),
            "views": [sum(v[i] for v in views) / len(views) for i in range(nv)],
            "iou": _mean_sd(means), "min": min(means), "max": max(means),
            "offset_cm": ([100 * sum(o[i] for o in offs) / len(offs) for i in range(3)]
                          if offs else None),
        }
    return table


def markdown_bodytrack(table: dict, missing: list[str]) -> str:
    nv = len(next(iter(table.values()))["views"])
    lines = ["# Hauberg & Pedersen (2011): the real 4-camera bodytrack frame", "",
             "Silhouette IoU of the fitted capsule model with each view's foreground mask "
             f"(no ground truth); target ≥ {IOU_TARGET:.2f} mean.", "",
             "| fit | " + " | ".join(f"view {i + 1}" for i in range(nv))
             + " | mean IoU | min – max over seeds | head offset (cm, neck frame) | seeds |",
             "|---|" + "---:|" * (nv + 4)]
    for t, name in BODYTRACK.items():
        row = table.get(t)
        if row is None:
            continue
        off = ("–" if row["offset_cm"] is None
               else "(" + ", ".join(f"{v:.1f}" for v in row["offset_cm"]) + ")")
        lines.append(f"| {name} | " + " | ".join(f"{v:.3f}" for v in row["views"])
                     + f" | {_cell(row['iou'], '{:.3f}')} | {row['min']:.3f} – {row['max']:.3f}"
                     f" | {off} | {row['seeds']} |")
    lines += ["", "Cells: per-view IoU averaged over tracker seeds "
              f"{SEEDS[0]}–{SEEDS[-1]}; mean IoU: mean ± std over the seeds. Head offset: the "
              "head capsule's fitted displacement in the neck's frame (x, y, z; z along the bone)."]
    if missing:
        lines += ["", f"Missing runs ({len(missing)}): " + ", ".join(missing)]
    return "\n".join(lines) + "\n"


def plot_bodytrack(table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [t for t in BODYTRACK if t in table]
    nv = len(table[names[0]]["views"])
    fig, ax = plt.subplots(figsize=(8, 3.6))
    width = 0.8 / len(names)
    for k, t in enumerate(names):
        xs = [i + (k - (len(names) - 1) / 2) * width for i in range(nv + 1)]
        bars = ax.bar(xs[:nv], table[t]["views"], width, label=t)
        ax.bar(xs[nv], table[t]["iou"][0], width, yerr=table[t]["iou"][1], capsize=3,
               color=bars.patches[0].get_facecolor())
    ax.axhline(IOU_TARGET, color="k", ls="--", lw=1, label=f"target {IOU_TARGET:.2f}")
    ax.set_xticks(range(nv + 1))
    ax.set_xticklabels([f"view {i + 1}" for i in range(nv)] + ["mean"])
    ax.set_ylim(0.4, 1.0)
    ax.set_ylabel("silhouette IoU")
    ax.set_title("real bodytrack frame: fitted model vs masks (mean over seeds)", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (never a half-written table)."""
    from torchmocap.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(text)


def main_bodytrack(runs_dir: Path, out: Path) -> int:
    runs, missing = load_bodytrack(runs_dir)
    if not runs:
        print(f"report: no metrics.json under {runs_dir}", file=sys.stderr)
        return 2
    table = summarise_bodytrack(runs)
    out.mkdir(parents=True, exist_ok=True)
    md = markdown_bodytrack(table, missing)
    _write_atomic(out / "bodytrack.md", md)
    plot_bodytrack(table, out / "bodytrack.png")
    print(md)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sweep", choices=sorted([*SWEEPS, "bodytrack"]))
    ap.add_argument("--runs", type=Path, default=None,
                    help="the sweep's run directory (default runs/<sweep>)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--particles", type=int, nargs="+", default=None,
                    help="particle counts to tabulate (default: the sweep's own)")
    args = ap.parse_args(argv)
    if args.sweep == "bodytrack":
        return main_bodytrack(args.runs or HERE / "runs" / "bodytrack", args.out)
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
    _write_atomic(args.out / f"{args.sweep}.md", md)
    plot(args.sweep, spec, table, args.out / f"{args.sweep}.png")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
