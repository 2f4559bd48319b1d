"""Fig. 8 outdoor with the fitted body: report of the runs of ``+experiment=ponsmoll2010/fig8``
with ``tracker=default`` (today's capsules) and ``tracker=default_anny`` (the subject's Anny body
fitted at the first frame, capsules fitted to it).

The Pons-Moll et al. (2010) Fig. 8 protocol (``conf/experiment/ponsmoll2010/fig8.yaml``): the
outdoor scenario (the skinned MakeHuman mesh, background clutter, noisy masks), six activities,
up to 75 frames at 25 fps. The default tracker (LS) is deterministic, so one tracker seed per
cell; the synthesis seed 0 is the table's, seeds 1 and 2 (other noise, clutter and IMU drift on
the same clips) show how much a difference between the bodies is the observations'. From the
repository root::

    export OMP_NUM_THREADS=1
    torchmocap-track -m +experiment=ponsmoll2010/fig8 tracker=default,default_anny seed=0 \\
        threads=1 glb.enabled=false hydra.sweep.dir=experiments/body/runs/fig8 \\
        'hydra.sweep.subdir=${data.clip.name}/${tracker.name}/seed${seed}'
    torchmocap-track -m +experiment=ponsmoll2010/fig8 tracker=default,default_anny seed=0 \\
        data.seed=1,2 threads=1 glb.enabled=false \\
        hydra.sweep.dir=experiments/body/runs/fig8_synthesis_seeds \\
        'hydra.sweep.subdir=synth${data.seed}/${data.clip.name}/${tracker.name}'
    python experiments/body/fig8.py

Writes ``results/fig8.md`` and ``results/fig8.png``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from torchmocap.atomic import atomic_path, write_text_atomic

HERE = Path(__file__).resolve().parent
CLIPS = ("walking", "jumping", "kicking", "basketball", "dancing", "arm_rotation")
TRACKERS = (("default", "capsules"), ("default_anny", "fitted Anny body"))


def _run(folder: Path) -> dict | None:
    f = folder / "metrics.json"
    if not f.is_file():
        return None
    m = json.loads(f.read_text())
    return {"orientation": m["orientation_error_deg"]["mean"], "mpjpe": m["mpjpe_mm"]["mean"]
            if isinstance(m["mpjpe_mm"], dict) else m["mpjpe_mm"],
            "seconds_per_frame": m["seconds_per_frame"], "frames": m["tracked_frames"],
            "height": (m.get("body_fit") or {}).get("height")}


def load(runs: Path, seeds_runs: Path) -> dict:
    """``{(synthesis seed, clip, tracker): row}``."""
    out = {}
    for clip in CLIPS:
        for tr, _ in TRACKERS:
            r = _run(runs / clip / tr / "seed0")
            if r is not None:
                out[0, clip, tr] = r
            for s in (1, 2):
                r = _run(seeds_runs / f"synth{s}" / clip / tr)
                if r is not None:
                    out[s, clip, tr] = r
    return out


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else float("nan")


def report(rows: dict) -> str:
    seeds = sorted({k[0] for k in rows})
    lines = [
        "# Fig. 8 outdoor: the default tracker (LS) with today's capsules and with the fitted "
        "Anny body",
        "",
        "Outdoor scenario (the skinned MakeHuman mesh), six activities, up to 75 frames at "
        "25 fps, one thread (`python experiments/body/fig8.py`; commands in its docstring). "
        "Cells: validation orientation error (deg, the Fig. 8 metric) / MPJPE (mm); "
        "capsules → fitted body. LS is deterministic: one tracker seed.",
        "",
        "## Synthesis seed 0 (the Fig. 8 table's observations)",
        "",
        "| activity | frames | orientation, capsules | orientation, fitted body | MPJPE, "
        "capsules | MPJPE, fitted body | fitted height (m) | s / frame |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for clip in CLIPS:
        a, b = rows.get((0, clip, "default")), rows.get((0, clip, "default_anny"))
        if a is None or b is None:
            continue
        worse = lambda x, y: f"**{y:.1f}**" if y > x else f"{y:.1f}"  # noqa: E731
        lines.append(
            f"| {clip} | {a['frames']} | {a['orientation']:.2f} | "
            f"{worse(a['orientation'], b['orientation'])} | {a['mpjpe']:.1f} | "
            f"{worse(a['mpjpe'], b['mpjpe'])} | {b['height']:.2f} | "
            f"{a['seconds_per_frame']:.2f} → {b['seconds_per_frame']:.2f} |")
    both = [c for c in CLIPS if (0, c, "default") in rows and (0, c, "default_anny") in rows]
    lines.append(
        f"| **all** | | **{_mean([rows[0, c, 'default']['orientation'] for c in both]):.2f}**"
        f" | **{_mean([rows[0, c, 'default_anny']['orientation'] for c in both]):.2f}** | "
        f"**{_mean([rows[0, c, 'default']['mpjpe'] for c in both]):.1f}** | "
        f"**{_mean([rows[0, c, 'default_anny']['mpjpe'] for c in both]):.1f}** | | |")
    lines += ["", "Bold: the fitted body worse than the capsules.", ""]
    if len(seeds) > 1:
        lines += ["## Every synthesis seed", "",
                  "Per activity: the fitted body's change against the capsules (orientation deg "
                  "/ MPJPE mm; negative = better), synthesis seeds " +
                  ", ".join(map(str, seeds)) + ", and their mean.", "",
                  "| activity | " + " | ".join(f"seed {s}" for s in seeds) + " | mean |",
                  "|---|" + "---:|" * (len(seeds) + 1)]
        for clip in CLIPS:
            cells, do, dm = [], [], []
            for s in seeds:
                a, b = rows.get((s, clip, "default")), rows.get((s, clip, "default_anny"))
                if a is None or b is None:
                    cells.append("–")
                    continue
                do.append(b["orientation"] - a["orientation"])
                dm.append(b["mpjpe"] - a["mpjpe"])
                cells.append(f"{do[-1]:+.2f} / {dm[-1]:+.1f}")
            lines.append(f"| {clip} | " + " | ".join(cells) +
                         f" | {_mean(do):+.2f} / {_mean(dm):+.1f} |")
        pairs = [(rows[k], rows[(k[0], k[1], "default_anny")]) for k in rows
                 if k[2] == "default" and (k[0], k[1], "default_anny") in rows]
        lines += ["", f"Over all {len(pairs)} pairs: orientation "
                  f"{_mean([a['orientation'] for a, _ in pairs]):.2f} → "
                  f"{_mean([b['orientation'] for _, b in pairs]):.2f} deg, MPJPE "
                  f"{_mean([a['mpjpe'] for a, _ in pairs]):.1f} → "
                  f"{_mean([b['mpjpe'] for _, b in pairs]):.1f} mm; the fitted body lower in "
                  f"{sum(b['orientation'] < a['orientation'] for a, b in pairs)} of "
                  f"{len(pairs)} (orientation) and "
                  f"{sum(b['mpjpe'] < a['mpjpe'] for a, b in pairs)} of {len(pairs)} (MPJPE).",
                  ""]
    return "\n".join(lines) + "\n"


def plot(rows: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds = sorted({k[0] for k in rows})
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, key, label in ((axes[0], "orientation", "orientation error (deg)"),
                           (axes[1], "mpjpe", "MPJPE (mm)")):
        for i, (tr, name) in enumerate(TRACKERS):
            xs, ys = [], []
            for c, clip in enumerate(CLIPS):
                for s in seeds:
                    r = rows.get((s, clip, tr))
                    if r is not None:
                        xs.append(c + (i - 0.5) * 0.3)
                        ys.append(r[key])
            ax.scatter(xs, ys, s=18, label=name, alpha=0.8)
        ax.set_xticks(range(len(CLIPS)), CLIPS, rotation=30, ha="right")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Fig. 8 outdoor, LS: capsules vs fitted Anny body (synthesis seeds "
                 f"{', '.join(map(str, seeds))})", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=HERE / "runs" / "fig8")
    ap.add_argument("--seeds-runs", type=Path, default=HERE / "runs" / "fig8_synthesis_seeds")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    rows = load(args.runs, args.seeds_runs)
    if not rows:
        raise SystemExit(f"no runs under {args.runs}")
    args.out.mkdir(parents=True, exist_ok=True)
    text = report(rows)
    write_text_atomic(args.out / "fig8.md", text)
    plot(rows, args.out / "fig8.png")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
