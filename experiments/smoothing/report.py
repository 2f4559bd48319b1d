"""The offline Kalman smoother against the trackers' own (filtered) estimates: table and plot
from the runs' ``metrics.json``.

The runs are made by the experiment config (from the repository root)::

    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=smoothing/kalman hydra/launcher=joblib
    python experiments/smoothing/report.py        # -> results/kalman.md, results/kalman.png

Each job writes ``runs/kalman/<scenario>/<clip>/<tracker>/seed<s>/metrics.json`` with the
smoothed errors (``orientation_error_deg``, ``mpjpe_mm``) and the tracker's own under
``filtered``. Per scenario, clip and tracker the table gives both (mean over frames, then over
seeds), the relative change, and the noise the smoother estimated (median over the rotation
DoFs of the measurement and acceleration stds); the last rows average over the clips.
``--runs`` and ``--out`` point elsewhere.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
METRICS = ("orientation_error_deg", "mpjpe_mm", "mpjpe_root_relative_mm")
#: reported when every run has it (trackers scored by Hauberg & Pedersen's eq. 16)
MARKERS = "marker_error_mm"


def load(runs_dir: Path) -> list[dict]:
    """One record per run: scenario, clip, tracker, seed, filtered and smoothed errors."""
    out = []
    for p in sorted(runs_dir.glob("*/*/*/seed*/metrics.json")):
        m = json.loads(p.read_text())
        if "filtered" not in m or "smoother" not in m:
            raise ValueError(f"{p}: not a smoothed run (no 'filtered' / 'smoother')")
        scenario, clip, tracker = p.parts[-5], p.parts[-4], p.parts[-3]
        keys = METRICS + ((MARKERS,) if MARKERS in m["filtered"] else ())
        out.append({
            "scenario": scenario, "clip": clip, "tracker": tracker,
            "seed": int(p.parts[-2][4:]),
            "filtered": {k: float(m["filtered"][k]) for k in keys},
            "smoothed": {k: float(m[k]["mean"]) for k in keys},
            "r_deg": m["smoother"].get("measurement_std_deg_median"),
            "q_deg": m["smoother"].get("acceleration_std_deg_median"),
            "clamped": int(m["smoother"].get("clamped", 0)),
        })
    return out


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else math.nan


def metrics_of(runs: list[dict]) -> tuple[str, ...]:
    """The measures of the table: METRICS, and the marker error when every run has it."""
    return METRICS + ((MARKERS,) if runs and all(MARKERS in r["filtered"] for r in runs)
                      else ())


def summarise(runs: list[dict]) -> list[dict]:
    """Rows per (scenario, tracker, clip) averaged over seeds, then per (scenario, tracker) the
    mean over clips (clip ``"mean"``)."""
    keys = sorted({(r["scenario"], r["tracker"], r["clip"]) for r in runs})
    measures = metrics_of(runs)
    rows = []
    for s, t, c in keys:
        sel = [r for r in runs if (r["scenario"], r["tracker"], r["clip"]) == (s, t, c)]
        rows.append({"scenario": s, "tracker": t, "clip": c, "seeds": len(sel),
                     **{f"{w}_{k}": _mean([r[w][k] for r in sel])
                        for w in ("filtered", "smoothed") for k in measures},
                     "r_deg": _mean([r["r_deg"] for r in sel]),
                     "q_deg": _mean([r["q_deg"] for r in sel])})
    for s, t in sorted({(r["scenario"], r["tracker"]) for r in rows}):
        sel = [r for r in rows if (r["scenario"], r["tracker"]) == (s, t)]
        rows.append({"scenario": s, "tracker": t, "clip": "mean", "seeds": len(sel),
                     **{k: _mean([r[k] for r in sel]) for k in sel[0]
                        if k.startswith(("filtered_", "smoothed_", "r_", "q_"))}})
    return rows


def _pct(a, b):
    return f"{100 * (b - a) / a:+.0f} %" if a else "–"


def markdown(rows: list[dict]) -> str:
    measures = METRICS + ((MARKERS,) if f"filtered_{MARKERS}" in rows[0] else ())
    lines = ["# Offline Kalman smoother vs the tracker's own estimates", "",
             "Constant-velocity Rauch–Tung–Striebel smoother per DoF, noise estimated by maximum "
             "likelihood (`+smoother@tracker.smoother=kalman`); errors over frames 1..T-1, mean "
             "over seeds. *filtered*: the tracker's per-frame estimates; *smoothed*: after the "
             "smoother. r, q: the fitted measurement / acceleration std (median over the "
             "rotation DoFs, degrees and degrees per frame²).", "",
             "| scenario | tracker | clip | orientation (°) filtered → smoothed | MPJPE (mm) "
             "filtered → smoothed | root-aligned MPJPE (mm) | "
             + ("marker error, eq. 16 (mm) | " if MARKERS in measures else "")
             + "r (°) | q (°/frame²) |",
             "|---|---|---|---|---|---|" + ("---|" if MARKERS in measures else "")
             + "---:|---:|"]
    for r in rows:
        bold = "**" if r["clip"] == "mean" else ""
        cells = []
        for k in measures:
            a, b = r[f"filtered_{k}"], r[f"smoothed_{k}"]
            cells.append(f"{bold}{a:.1f} → {b:.1f} ({_pct(a, b)}){bold}")
        lines.append(f"| {r['scenario']} | `{r['tracker']}` | {r['clip']} | " + " | ".join(cells)
                     + f" | {r['r_deg']:.1f} | {r['q_deg']:.1f} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({(r["scenario"], r["tracker"]) for r in rows})
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.6), squeeze=False)
    for ax, (s, t) in zip(axes[0], groups):
        sel = [r for r in rows if (r["scenario"], r["tracker"]) == (s, t)]
        x = list(range(len(sel)))
        ax.bar([i - 0.2 for i in x], [r["filtered_mpjpe_mm"] for r in sel], 0.4,
               label="filtered", color="0.6")
        ax.bar([i + 0.2 for i in x], [r["smoothed_mpjpe_mm"] for r in sel], 0.4,
               label="smoothed", color="tab:blue")
        ax.set_xticks(x, [r["clip"] for r in sel], rotation=45, ha="right", fontsize=8)
        ax.set_title(f"{t}, {s}", fontsize=9)
        ax.set_ylabel("MPJPE (mm)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    from torchmocap.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (never a half-written table)."""
    from torchmocap.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, default=HERE / "runs" / "kalman")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--name", default="kalman", help="file stem of the table and the plot")
    args = ap.parse_args(argv)
    try:
        runs = load(args.runs)
    except ValueError as e:
        print(f"report: {e}", file=sys.stderr)
        return 2
    if not runs:
        print(f"report: no metrics.json under {args.runs}", file=sys.stderr)
        return 2
    rows = summarise(runs)
    args.out.mkdir(parents=True, exist_ok=True)
    _write_atomic(args.out / f"{args.name}.md", markdown(rows))
    plot(rows, args.out / f"{args.name}.png")
    print(f"report: {len(runs)} runs -> {args.out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
