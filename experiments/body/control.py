"""The control table with many bodies: report of the runs of ``+experiment=body/control``.

Clean observations (``clean`` scenario, synthesis seed 0, 30 frames) of the walking, jumping and
basketball clips rendered from five Anny phenotypes (``data=anny_clean``: child, heavy, slim,
tall, female) and from the MakeHuman mesh (``data=skinned_clean``), each tracked by the default
tracker (LS) with today's anthropometric capsules (``tracker=default``) and with the subject's
Anny body fitted at the first frame (``tracker=default_anny``, ``body_fit=anny``). From the
repository root::

    export OMP_NUM_THREADS=1
    torchmocap-track -m +experiment=body/control data=anny_clean \\
        data.scenario_overrides.phenotype=child,heavy,slim,tall,female
    torchmocap-track -m +experiment=body/control data=skinned_clean
    python experiments/body/control.py

Writes ``results/control.md`` and ``results/control.png`` (MPJPE per body and clip, both
bodies). The same table at the clips' own length (up to 75 frames)::

    torchmocap-track -m +experiment=body/control data=skinned_clean data.clip.frames=75 \\
        hydra.sweep.dir=experiments/body/runs/control75
    python experiments/body/control.py --runs experiments/body/runs/control75 --name control75

A table missing some (body, clip) pairs says so in its first lines (partial).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
CLIPS = ("walking", "jumping", "basketball")
BODIES = (("anny_clean", "child"), ("anny_clean", "heavy"), ("anny_clean", "slim"),
          ("anny_clean", "tall"), ("anny_clean", "female"), ("skinned_clean", "makehuman"))
TRACKERS = (("default", "capsules"), ("default_anny", "fitted Anny body"))


def load(runs: Path) -> dict:
    out = {}
    for data, body in BODIES:
        for clip in CLIPS:
            for tr, _ in TRACKERS:
                f = runs / data / body / clip / tr / "metrics.json"
                if f.is_file():
                    out[body, clip, tr] = json.loads(f.read_text())
    return out


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else float("nan")


def report(runs: Path, out: Path, stem: str = "control") -> str:
    m = load(runs)
    if not m:
        raise SystemExit(f"no runs under {runs}")
    frames = sorted({v["frames"] for v in m.values()})
    lines = [
        "# Control with many bodies: default tracker (LS), today's capsules vs the fitted Anny "
        "body",
        "",
        f"Clean scenario, synthesis seed 0, {'/'.join(map(str, frames))} frames per clip "
        "(`+experiment=body/control`, `python experiments/body/control.py`; one thread, "
        "a shared loaded 2-core machine). Cells: MPJPE (mm) / validation orientation error (deg), "
        "capsules → fitted body. Height: the fitted body's standing height minus the rendered "
        "body's (cm); IoU: the capsules' silhouette IoU at the first pose, anthropometric → "
        "fitted; s/frame: seconds per tracked frame (capsules → fitted; the fit itself, once, "
        "in `fit s`).",
        "",
        "| body | clip | MPJPE mm | orientation ° | height err cm | IoU | s/frame | fit s |",
        "|---|---|---|---|---|---|---|---|"]
    missing = [f"{body}/{clip}" for _, body in BODIES for clip in CLIPS
               if not all((body, clip, tr) in m for tr, _ in TRACKERS)]
    if missing:
        lines[2:2] = [f"**Partial table**: {len(missing)} of {len(BODIES) * len(CLIPS)} "
                      f"(body, clip) pairs not run ({', '.join(missing)}).", ""]
    rows = {}
    for _, body in BODIES:
        for clip in CLIPS:
            a, b = m.get((body, clip, "default")), m.get((body, clip, "default_anny"))
            if a is None or b is None:
                continue
            fit = b.get("body_fit") or {}
            h = fit.get("height_error_m")
            r = dict(mp=(a["mpjpe_mm"]["mean"], b["mpjpe_mm"]["mean"]),
                     ori=(a["orientation_error_deg"]["mean"], b["orientation_error_deg"]["mean"]),
                     spf=(a["seconds_per_frame"], b["seconds_per_frame"]),
                     h=None if h is None else 100 * h, iou=(fit.get("iou_before"),
                                                           fit.get("iou_after")),
                     fit_s=fit.get("seconds"))
            rows[body, clip] = r
            height = "-" if r["h"] is None else f"{r['h']:+.2f}"
            lines.append(
                f"| {body} | {clip} | {r['mp'][0]:.1f} → **{r['mp'][1]:.1f}** | "
                f"{r['ori'][0]:.2f} → {r['ori'][1]:.2f} | {height} | "
                f"{r['iou'][0]:.3f} → {r['iou'][1]:.3f} | {r['spf'][0]:.2f} → {r['spf'][1]:.2f} | "
                f"{r['fit_s']:.1f} |")
    anny = [k for k in rows if k[0] != "makehuman"]
    mh = [k for k in rows if k[0] == "makehuman"]
    lines += ["", "Summary:", ""]
    for name, keys in (("Anny phenotypes (5 x 3 clips)", anny), ("MakeHuman mesh (3 clips)", mh)):
        if not keys:
            continue
        def mean(q, i, keys=keys):
            return _mean([rows[k][q][i] for k in keys])

        lines.append(f"- {name}: MPJPE {mean('mp', 0):.1f} → {mean('mp', 1):.1f} mm, "
                     f"orientation {mean('ori', 0):.2f} → {mean('ori', 1):.2f}°, s/frame "
                     f"{mean('spf', 0):.3f} → {mean('spf', 1):.3f} (ratio "
                     f"{mean('spf', 1) / mean('spf', 0):.2f})")
    for _, body in BODIES[:-1]:
        keys = [k for k in anny if k[0] == body]
        if keys:
            mp = _mean([rows[k]["mp"][1] for k in keys])
            h = max(abs(rows[k]["h"]) for k in keys)
            lines.append(f"- {body}: fitted-body MPJPE {mp:.1f} mm (capsules "
                         f"{_mean([rows[k]['mp'][0] for k in keys]):.1f}), height error max "
                         f"{h:.2f} cm")
    if anny:
        lines.append(f"- height error over every Anny run: max "
                     f"{max(abs(rows[k]['h']) for k in anny):.2f} cm")
    text = "\n".join(lines) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    from torchmocap.atomic import write_text_atomic

    write_text_atomic(out / f"{stem}.md", text)
    _plot(rows, out / f"{stem}.png")
    return text


def _plot(rows: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from torchmocap.atomic import atomic_path

    bodies = [b for _, b in BODIES]
    fig, axes = plt.subplots(1, len(CLIPS), figsize=(12, 3.6), sharey=True)
    x = np.arange(len(bodies))
    for ax, clip in zip(axes, CLIPS):
        caps = [rows.get((b, clip), {"mp": (np.nan, np.nan)})["mp"][0] for b in bodies]
        fit = [rows.get((b, clip), {"mp": (np.nan, np.nan)})["mp"][1] for b in bodies]
        ax.bar(x - 0.2, caps, 0.4, label="today's capsules")
        ax.bar(x + 0.2, fit, 0.4, label="fitted Anny body")
        ax.axhline(20, color="k", lw=0.8, ls="--")
        ax.set_xticks(x, bodies, rotation=30)
        ax.set_title(clip)
    axes[0].set_ylabel("MPJPE (mm)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, default=HERE / "runs" / "control")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--name", default="control", help="file stem of the table and plot")
    a = ap.parse_args()
    print(report(a.runs, a.out, a.name))
