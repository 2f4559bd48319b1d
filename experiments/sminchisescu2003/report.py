"""Sminchisescu & Triggs (2003), §5.2: table and per-frame 3D error plot of the monocular
tracking runs (KJS + CSS vs CSS vs SS) from their ``metrics.json`` (and ``track.npz``).

The runs are made by the experiment config (from the repository root)::

    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=sminchisescu2003/tracking \
        hydra/launcher=joblib
    python experiments/sminchisescu2003/report.py          # -> results/tracking.md, .png

Each job writes ``runs/tracking/<clip>/<tracker>/seed<s>/metrics.json``. Per clip and tracker the
table gives the MPJPE of the estimate (mean over frames and seeds, ± the spread of the per-seed
means), the validation-bone orientation error (Pons-Moll eq. 19, bones spine, shoulders, hips),
seconds per frame, and — when ``metrics.json`` carries the mixture's hypotheses
(``hypotheses.mpjpe_top_mm``, ``hypotheses.mpjpe_best_mm``, ``hypotheses.modes``, each with a
``mean``) — the MPJPE of the top-weighted and of the best hypothesis and the modes kept; runs
that carry ``mpjpe_root_relative_mm`` add the root-aligned MPJPE (pelvis at the origin in both
poses: the pose without the whole body's global offset, which one camera sees worst). The
plot shows the per-frame MPJPE (from ``track.npz``, else ``mpjpe_mm.per_frame``, else the
orientation error's ``per_frame``) of each tracker, averaged over seeds, one panel per clip.
Runs made with a smoother (``+smoother@tracker.smoother=viterbi``) carry ``filtered``: the table
then gives the smoothed and the filtered MPJPE side by side (the orientation error and the plot
are the smoothed track's). Runs made with a chain of smoothers (``smoother=viterbi_kalman``) add
the root-aligned MPJPE and orientation error after each stage but the last (``after viterbi``:
the chain's own ablation). ``--runs`` and ``--out`` point elsewhere (e.g. a tiny validation
sweep).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUNS = HERE / "runs" / "tracking"
RESULTS = HERE / "results"
CLIPS = {"dance_cmu21": "dance (CMU21)", "salsa": "salsa (CMU 60_12)",
         "boxing": "boxing (CMU21 box-1)"}
TRACKERS = {"kjs": "KJS + CSS", "css": "CSS", "ss": "SS"}
#: labels of the run directories (``tracker.name``) beyond the three presets
LABELS = {**TRACKERS, "kjs_continuations": "KJS + CSS, continuations = 4"}
SEEDS = [0, 1, 2, 3, 4]


def _per_frame(run_dir: Path, m: dict) -> tuple[list[float], str]:
    """Per-frame 3D error of a run: MPJPE (mm) from track.npz or metrics.json, else the
    orientation error (deg)."""
    npz = run_dir / "track.npz"
    if npz.is_file():
        import numpy as np

        with np.load(npz) as z:
            if "mpjpe_mm" in z:
                return [float(v) for v in z["mpjpe_mm"]], "MPJPE (mm)"
    pf = m.get("mpjpe_mm", {}).get("per_frame")
    if pf:
        return [float(v) for v in pf], "MPJPE (mm)"
    return [float(v) for v in m["orientation_error_deg"]["per_frame"]], \
        "orientation error (deg)"


def load_runs(runs: Path, clips, trackers, seeds) -> tuple[dict, list[str]]:
    """``{(clip, tracker): [(metrics, run_dir), ...]}`` and the missing / failed run dirs."""
    out, missing = {}, []
    for c in clips:
        for t in trackers:
            for s in seeds:
                d = runs / c / t / f"seed{s}"
                p = d / "metrics.json"
                if p.is_file():
                    out.setdefault((c, t), []).append((json.loads(p.read_text()), d))
                else:
                    why = " (failed)" if (d / "failure.json").is_file() else ""
                    missing.append(f"{d.relative_to(runs)}{why}")
    return out, missing


def _mean_spread(vals: list[float]) -> tuple[float, float]:
    n = len(vals)
    m = sum(vals) / n
    sd = math.sqrt(sum((v - m) ** 2 for v in vals) / (n - 1)) if n > 1 else 0.0
    return m, sd


def summarise(runs: dict) -> dict:
    table = {}
    for key, rs in runs.items():
        ms = [m for m, _ in rs]
        row = {"seeds": len(ms),
               "mpjpe": _mean_spread([m["mpjpe_mm"]["mean"] for m in ms]),
               "ori": _mean_spread([m["orientation_error_deg"]["mean"] for m in ms]),
               "spf": sum(m["seconds_per_frame"] for m in ms) / len(ms),
               "frames": ms[0]["frames"], "particles": ms[0].get("num_particles")}
        if all("mpjpe_root_relative_mm" in m for m in ms):
            row["root"] = _mean_spread([m["mpjpe_root_relative_mm"]["mean"] for m in ms])
        if all(isinstance(m.get("filtered"), dict) for m in ms):  # smoothed runs
            row["filtered"] = _mean_spread([m["filtered"]["mpjpe_mm"] for m in ms])
            if all("mpjpe_root_relative_mm" in m["filtered"] for m in ms):
                row["root_filtered"] = _mean_spread(
                    [m["filtered"]["mpjpe_root_relative_mm"] for m in ms])
        stages = [(m.get("smoother") or {}).get("stages") for m in ms]
        if all(isinstance(st, list) and st and all("errors" in x for x in st) for st in stages):
            # the errors after each stage of a chain but the last (= the top-level errors)
            row["stages"] = [
                (stages[0][k]["name"],
                 _mean_spread([st[k]["errors"]["mpjpe_root_relative_mm"] for st in stages]),
                 _mean_spread([st[k]["errors"]["orientation_error_deg"] for st in stages]))
                for k in range(len(stages[0]) - 1)]
        hyp = [m.get("hypotheses") for m in ms]
        if all(isinstance(h, dict) for h in hyp):
            for k in ("mpjpe_top_mm", "mpjpe_best_mm", "mpjpe_root_relative_top_mm",
                      "mpjpe_root_relative_best_mm", "modes"):
                vals = [h[k]["mean"] if isinstance(h.get(k), dict) else h.get(k) for h in hyp]
                if all(isinstance(v, (int, float)) for v in vals):
                    row[k] = _mean_spread([float(v) for v in vals])
        curves = [_per_frame(d, m) for m, d in rs]
        n = min(len(c[0]) for c in curves)
        row["curve"] = [sum(c[0][i] for c in curves) / len(curves) for i in range(n)]
        row["curve_label"] = curves[0][1]
        table[key] = row
    return table


def markdown(table: dict, clips, trackers, missing: list[str]) -> str:
    has_h = any("mpjpe_best_mm" in r for r in table.values())
    has_f = any("filtered" in r for r in table.values())
    has_r = any("root" in r for r in table.values())
    head = ("| clip | tracker | MPJPE, smoothed (mm) | MPJPE, filtered (mm) |" if has_f
            else "| clip | tracker | MPJPE (mm) |")
    sep = "|---|---|---:|" + ("---:|" if has_f else "")
    if has_r:
        head += (" root-aligned, smoothed (mm) | root-aligned, filtered (mm) |" if has_f
                 else " root-aligned MPJPE (mm) |")
        sep += "---:|" + ("---:|" if has_f else "")
    head += " orientation error (deg) |"
    sep += "---:|"
    stage_names = next((tuple(n for n, _, _ in r["stages"]) for r in table.values()
                        if r.get("stages")), ())
    for n in stage_names:
        head += f" root-aligned after {n} (mm) | orientation error after {n} (deg) |"
        sep += "---:|---:|"
    if has_h:
        head += " top hypothesis (mm) | best hypothesis (mm) |"
        sep += "---:|---:|"
        if has_r:
            head += " best hypothesis, root-aligned (mm) |"
            sep += "---:|"
        head += " modes |"
        sep += "---:|"
    head += " s / frame | seeds |"
    sep += "---:|---:|"
    lines = ["# Sminchisescu & Triggs (2003), §5.2 — monocular tracking", "",
             "Mean over frames and tracker seeds (± spread of the per-seed means); "
             "paper: qualitative only (Fig. 7: KJS + CSS tracks a 4 s dance; no numbers).", "",
             head, sep]
    for c in clips:
        for t in trackers:
            r = table.get((c, t))
            if r is None:
                continue
            cells = [CLIPS.get(c, c), LABELS.get(t, t),
                     f"{r['mpjpe'][0]:.1f} ± {r['mpjpe'][1]:.1f}"]
            if has_f:
                f = r.get("filtered")
                cells.append(f"{f[0]:.1f} ± {f[1]:.1f}" if f else "–")
            if has_r:
                for k in ("root", "root_filtered")[: 2 if has_f else 1]:
                    cells.append(f"{r[k][0]:.1f} ± {r[k][1]:.1f}" if k in r else "–")
            cells.append(f"{r['ori'][0]:.2f} ± {r['ori'][1]:.2f}")
            st = {n: (a, o) for n, a, o in r.get("stages", [])}
            for n in stage_names:
                a, o = st.get(n, (None, None))
                cells += [f"{a[0]:.1f} ± {a[1]:.1f}" if a else "–",
                          f"{o[0]:.2f} ± {o[1]:.2f}" if o else "–"]
            if has_h:
                keys = ["mpjpe_top_mm", "mpjpe_best_mm"]
                keys += ["mpjpe_root_relative_best_mm"] if has_r else []
                for k in keys:
                    cells.append(f"{r[k][0]:.1f} ± {r[k][1]:.1f}" if k in r else "–")
                cells.append(f"{r['modes'][0]:.1f}" if "modes" in r else "–")
            cells += [f"{r['spf']:.2f}", str(r["seeds"])]
            lines.append("| " + " | ".join(cells) + " |")
    if missing:
        lines += ["", f"Missing runs ({len(missing)}): " + ", ".join(missing)]
    return "\n".join(lines) + "\n"


def plot(table: dict, clips, trackers, path: Path, fps: float = 25.0) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clips = [c for c in clips if any((c, t) in table for t in trackers)]
    fig, axes = plt.subplots(len(clips), 1, figsize=(7, 2.4 * len(clips) + 0.4), squeeze=False,
                             sharex=True)
    label = "3D error"
    for ax, c in zip(axes[:, 0], clips):
        for t in trackers:
            r = table.get((c, t))
            if r is None:
                continue
            xs = [(i + 1) / fps for i in range(len(r["curve"]))]
            ax.plot(xs, r["curve"], lw=1.2, label=LABELS.get(t, t))
            label = r["curve_label"]
        ax.set_title(CLIPS.get(c, c), fontsize=9)
        ax.set_ylabel(label, fontsize=8)
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", default=str(RUNS))
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--clips", default=",".join(CLIPS))
    ap.add_argument("--trackers", default=",".join(TRACKERS))
    ap.add_argument("--seeds", default=",".join(str(s) for s in SEEDS))
    args = ap.parse_args(argv)
    clips = [c for c in args.clips.split(",") if c]
    trackers = [t for t in args.trackers.split(",") if t]
    seeds = [int(s) for s in args.seeds.split(",") if s]
    runs, missing = load_runs(Path(args.runs), clips, trackers, seeds)
    if not runs:
        print(f"no runs under {args.runs}; run `torchmocap-track -m "
              "+experiment=sminchisescu2003/tracking` first", file=sys.stderr)
        return 1
    table = summarise(runs)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tracking.md").write_text(markdown(table, clips, trackers, missing))
    plot(table, clips, trackers, out / "tracking.png")
    print(f"wrote {out / 'tracking.md'} and tracking.png"
          + (f" ({len(missing)} runs missing)" if missing else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
