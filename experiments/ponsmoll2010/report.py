"""Pons-Moll et al. (2010): tables and plots of Figs. 8, 9a, 10 and the control experiment, from
the runs' ``metrics.json``.

The runs are made by the experiment configs (from the repository root)::

    OMP_NUM_THREADS=1 torchmocap-track -m +experiment=ponsmoll2010/fig8 hydra/launcher=joblib
    python experiments/ponsmoll2010/report.py fig8        # -> results/fig8.md, results/fig8.png

(likewise ``fig9a``, ``fig10``, ``control``, ``body_fit``; ``all`` reports every figure whose
runs exist).
Each job writes ``runs/<figure>/<...>/metrics.json`` (its directory names the clip, tracker and
seed); a figure's report needs all of its jobs and says which are missing or failed.
Cells read ``mean ± std over frames, bones and seeds (± spread of the per-seed means)``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUNS = HERE / "runs"
RESULTS = HERE / "results"

ACTIVITIES = {"walking": "walking", "jumping": "jumping", "kicking": "kicking",
              "basketball": "basketball", "dancing": "dancing", "arm_rotation": "arm rotation"}
METHODS = ["l", "ls", "g", "gs", "rs", "p", "p_fidelity", "p_prior", "p_prior_refined"]
PAPER_FIG8 = {"p": "**10.78 ± 8.5**", "gs": "not in Fig. 8", "g": "above P (GL)",
              "rs": "not in Fig. 8", "ls": "above P", "l": "above P", "p_fidelity": "–",
              "p_prior": "–", "p_prior_refined": "–"}
SEEDS = [0, 1, 2]
#: column labels
NAMES = {**{m: m.upper() for m in METHODS}, "p_fidelity": "P, fidelity options",
         "p_prior": "P, fidelity + temporal prior",
         "p_prior_refined": "P, fidelity + temporal prior + local refinement"}


def load(figure: str, *parts: str) -> dict | None:
    """metrics.json of one job, or None (missing / failed)."""
    p = RUNS / figure / Path(*parts) / "metrics.json"
    if not p.is_file():
        return None
    return json.loads(p.read_text())


def runs_of(figure: str, *parts: str, seeds=SEEDS) -> list[dict]:
    out, missing = [], []
    for s in seeds:
        m = load(figure, *parts, f"seed{s}")
        if m is None:
            missing.append(str(Path(figure, *parts, f"seed{s}")))
        else:
            out.append(m)
    if missing:
        failed = [m for m in missing if (RUNS / m / "failure.json").is_file()]
        raise SystemExit(f"{figure}: missing runs {missing} (failed: {failed}); run "
                         f"`torchmocap-track -m +experiment=ponsmoll2010/{figure}` first")
    return out


def combine(runs: list[dict]) -> dict:
    """Pool runs of several tracker seeds: mean error, std over frames x bones x seeds, the
    spread (std) of the per-seed means, per-bone means and per-frame curves averaged over
    seeds."""
    n = len(runs)
    oris = [r["orientation_error_deg"] for r in runs]
    mean = sum(o["mean"] for o in oris) / n
    std = math.sqrt(sum(o["std"] ** 2 + (o["mean"] - mean) ** 2 for o in oris) / n)
    spread = math.sqrt(sum((o["mean"] - mean) ** 2 for o in oris) / max(n - 1, 1))
    bones = list(oris[0]["per_bone"])
    per_bone = {b: sum(o["per_bone"][b] for o in oris) / n for b in bones}
    per_bone_frame = {b: [sum(v) / n for v in zip(*(o["per_bone_frame"][b] for o in oris))]
                      for b in bones}
    out = {"ori_mean": mean, "ori_std": std, "seed_spread": spread, "seeds": n,
           "ori_per_bone": per_bone, "ori_per_bone_frame": per_bone_frame,
           "seconds_per_frame": sum(r["seconds_per_frame"] for r in runs) / n,
           "frames": runs[0]["frames"], "per_seed": [o["mean"] for o in oris]}
    below = [r["estimate_energy_below_truth"] for r in runs
             if "estimate_energy_below_truth" in r]
    if below:
        out["below"] = sum(below) / len(below)
    return out


def cell(r: dict) -> str:
    if r.get("seeds", 1) > 1:
        return f"{r['ori_mean']:.1f} ± {r['ori_std']:.1f} (±{r['seed_spread']:.1f})"
    return f"{r['ori_mean']:.1f} ± {r['ori_std']:.1f}"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def fig8() -> str:
    rows = {(a, m): combine(runs_of("fig8", a, m)) for a in ACTIVITIES for m in METHODS}
    p = rows[("walking", "p")]
    lines = ["# Fig. 8: validation orientation error (deg): mean ± std over frames, the 5 "
             "validation sensors and tracker seeds 0-2 (± spread of the per-seed means); outdoor "
             "scenario, up to 75 frames at 25 fps, 200 particles x 15 layers "
             f"(`+experiment=ponsmoll2010/fig8`, {p['seeds']} seeds per cell)", "",
             "| activity | " + " | ".join(NAMES[m] for m in METHODS) + " |",
             "|---|" + "---|" * len(METHODS)]
    for a, label in ACTIVITIES.items():
        lines.append(f"| {label} ({rows[(a, 'p')]['frames'] - 1} frames) | "
                     + " | ".join(cell(rows[(a, m)]) for m in METHODS) + " |")
    allm = {m: [rows[(a, m)] for a in ACTIVITIES] for m in METHODS}
    mean = {m: sum(r["ori_mean"] for r in v) / len(v) for m, v in allm.items()}
    std = {m: math.sqrt(sum(r["ori_std"] ** 2 + (r["ori_mean"] - mean[m]) ** 2 for r in v)
                        / len(v)) for m, v in allm.items()}
    lines.append("| **all** | " + " | ".join(f"**{mean[m]:.1f} ± {std[m]:.1f}**"
                                                for m in METHODS) + " |")
    lines.append("| s / frame (1 core) | " + " | ".join(
        f"{sum(r['seconds_per_frame'] for r in allm[m]) / len(allm[m]):.2f}" for m in METHODS)
        + " |")
    lines.append("| paper (8 sequences) | " + " | ".join(PAPER_FIG8[m] for m in METHODS)
                 + " |")
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4))
    w = 0.8 / len(METHODS)
    for k, m in enumerate(METHODS):
        ax.bar([i + (k - (len(METHODS) - 1) / 2) * w for i in range(len(ACTIVITIES))],
               [rows[(a, m)]["ori_mean"] for a in ACTIVITIES], w, label=NAMES[m],
               yerr=[rows[(a, m)]["seed_spread"] for a in ACTIVITIES], capsize=2)
    ax.set_xticks(range(len(ACTIVITIES)))
    ax.set_xticklabels(list(ACTIVITIES.values()), fontsize=8)
    ax.set_ylabel("validation error (deg)")
    ax.axhline(10.78, color="k", ls=":", lw=1, label="paper P")
    ax.set_title("bars: seed spread", fontsize=8)
    ax.legend(fontsize=7, ncol=4)
    fig.tight_layout()
    fig.savefig(RESULTS / "fig8.png", dpi=110)
    plt.close(fig)
    return "\n".join(lines)


def fig9a() -> str:
    counts = [25, 50, 100, 200]
    res = {(m, n): combine(runs_of("fig9a", m, f"n{n}")) for m in ("gs", "p") for n in counts}
    lines = ["# Fig. 9a: validation error (deg) vs number of particles, walking clip, outdoor, "
             "15 layers, 75 frames, tracker seeds 0-2 (mean ± std over frames, bones and seeds; "
             "± spread of the per-seed means) (`+experiment=ponsmoll2010/fig9a`)", "",
             "| particles | " + " | ".join(str(n) for n in counts) + " |",
             "|---|" + "---|" * len(counts)]
    for m in ("gs", "p"):
        lines.append(f"| {m.upper()} | " + " | ".join(cell(res[(m, n)]) for n in counts) + " |")
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for m in ("gs", "p"):
        ax.errorbar(counts, [res[(m, n)]["ori_mean"] for n in counts],
                    [res[(m, n)]["seed_spread"] for n in counts], marker="o", capsize=3,
                    label=f"{m.upper()} (bars: seed spread)")
    ax.set_xscale("log")
    ax.minorticks_off()
    ax.set_xticks(counts)
    ax.set_xticklabels([str(n) for n in counts])
    ax.set_xlabel("particles")
    ax.set_ylabel("validation error (deg)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "fig9a.png", dpi=110)
    plt.close(fig)
    return "\n".join(lines)


def fig10() -> str:
    noises = [("none", "p_nonoise"), ("Gaussian on passive parameters", "p_gaussian"),
              ("vMF, κ = 1000", "p")]
    paper = {"p_nonoise": 26.8, "p_gaussian": 13.0, "p": 7.3}
    fid = [("none, fidelity options", "p_fidelity_nonoise"),
           ("Gaussian, fidelity options", "p_fidelity_gaussian"),
           ("vMF, fidelity options", "p_fidelity")]
    ref = [("none, default tracker", "p_prior_refined_nonoise"),
           ("Gaussian, default tracker", "p_prior_refined_gaussian"),
           ("vMF, default tracker", "p_prior_refined")]
    for extra in (fid, ref):  # optional row groups, each once all three sweeps exist
        if all((RUNS / "fig10" / t).is_dir() for _, t in extra):
            noises += extra
            paper.update({t: paper[b] for (_, t), b in zip(extra, ("p_nonoise", "p_gaussian",
                                                                     "p"))})
    res = {t: combine(runs_of("fig10", t)) for _, t in noises}
    lines = ["# Fig. 10: left-hip validation error (deg) of P with three sensor-noise models, "
             "walking clip with 5-10 deg sensor misalignment (studio), 200 x 15, 75 frames, "
             "tracker seeds 0-2 (`+experiment=ponsmoll2010/fig10`)", "",
             "| noise model (preset) | left hip (ours) | all 5 sensors (ours) | left hip (paper) |",
             "|---|---|---|---|"]
    for label, t in noises:
        r = res[t]
        lines.append(f"| {label} (`{t}`) | {r['ori_per_bone']['l_hip']:.1f} | {cell(r)} | "
                     f"{paper[t]} |")
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for label, t in noises:
        y = res[t]["ori_per_bone_frame"]["l_hip"]
        ax.plot([(i + 1) / 25 for i in range(len(y))], y, label=label,
                ls="--" if "fidelity" in t else ":" if "refined" in t else "-")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("left hip error (deg), mean of 3 seeds")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(RESULTS / "fig10.png", dpi=110)
    plt.close(fig)
    return "\n".join(lines)


def control() -> str:
    conditions = [("capsules, clean, fitted truth", "capsules_clean_fitted"),
                  ("capsules, clean", "capsules_clean"),
                  ("skinned mesh, clean", "skinned_clean"),
                  ("skinned mesh, outdoor", "skinned_outdoor")]
    acts = ["walking", "jumping", "basketball"]
    res = {(c, a): combine(runs_of("control", c, a)) for _, c in conditions for a in acts}
    lines = ["# Control: P (200 x 15) with observations from the tracker's own capsules vs the "
             "skinned mesh; 75 frames, seeds 0-2 (`+experiment=ponsmoll2010/control`). Cells: "
             "validation error (deg) mean ± std (± seed spread); in brackets the fraction of "
             "frames whose estimate has a lower energy than the true pose.", "",
             "| observations (data option) | " + " | ".join(acts) + " |",
             "|---|" + "---|" * len(acts)]
    for label, c in conditions:
        lines.append(f"| {label} (`{c}`) | " + " | ".join(
            f"{cell(res[(c, a)])} [{res[(c, a)]['below']:.2f}]" for a in acts) + " |")
    return "\n".join(lines)


#: the fidelity ablation's variants, cumulative, in the order they are reported
VARIANTS = ["baseline", "eq18", "propagate", "motion", "floor", "limits", "body", "alpha",
            "occlusion_vmf", "prior", "exact_sensors", "occlusion"]


def fidelity() -> str:
    root = RUNS / "fidelity"
    variants = [v for v in VARIANTS if (root / v).is_dir()]
    variants += sorted(p.name for p in root.iterdir() if p.is_dir() and p.name not in VARIANTS)
    conditions = [("capsules, clean, fitted truth", "capsules_clean_fitted"),
                  ("skinned mesh, outdoor", "skinned_outdoor")]
    acts = ["walking", "jumping", "basketball"]
    head = " | ".join(f"{lab.split(',')[0]}: {a}" for lab, _ in conditions for a in acts)
    lines = ["# P fidelity ablation: validation error (deg), mean (± seed spread) over tracker "
             "seeds 0-2, 75 frames, 200 x 15; in brackets the fraction of frames whose estimate "
             "beats the truth's energy. Variants are cumulative (each adds its options to the "
             "previous one; see the README). (`+experiment=ponsmoll2010/fidelity`)", "",
             f"| variant | {head} | capsules mean | outdoor mean |",
             "|---|" + "---|" * (len(conditions) * len(acts) + 2)]
    for v in variants:
        cells, means = [], []
        for _, c in conditions:
            if not (root / v / c).is_dir():  # a variant run on one condition only
                cells += ["–"] * len(acts)
                means.append(None)
                continue
            ms = []
            for a in acts:
                r = combine(runs_of(f"fidelity/{v}", c, a))
                cells.append(f"{r['ori_mean']:.1f} (±{r['seed_spread']:.1f}) [{r['below']:.2f}]")
                ms.append(r["ori_mean"])
            means.append(sum(ms) / len(ms))
        lines.append(f"| {v} | " + " | ".join(cells) + " | "
                     + " | ".join("–" if m is None else f"**{m:.1f}**" for m in means) + " |")
    return "\n".join(lines)


LONG_CLIPS = {"boxing_long": "boxing (CMU21 box-1)",
              "jumping_jack_long": "jumping jacks (CMU21)"}
LONG_METHODS = ["ls", "p", "p_fidelity", "p_prior", "p_prior_refined"]


def long() -> str:
    """20 s excerpts: LS vs P — mean error, and the error of the last 5 s against the first 5 s
    (a local optimiser that loses track does not come back)."""
    found = {(c, m): [r for r in (load("long", c, m, f"seed{s}") for s in SEEDS) if r]
             for c in LONG_CLIPS for m in LONG_METHODS}
    clips = {c: label for c, label in LONG_CLIPS.items()
             if all(found[(c, m)] for m in LONG_METHODS)}
    if not clips:
        raise SystemExit("long: no clip has runs of every tracker; run "
                         "`torchmocap-track -m +experiment=ponsmoll2010/long` first")
    rows = {(c, m): combine(found[(c, m)]) for c in clips for m in LONG_METHODS}
    lines = ["# Long excerpts: validation orientation error (deg), outdoor scenario, 500 frames "
             "(20 s at 25 fps), mean ± std over frames, sensors and tracker seeds (± spread of "
             "the per-seed means); first and last 5 s separately "
             "(`+experiment=ponsmoll2010/long`)", "",
             "| clip | tracker | all frames | first 5 s | last 5 s | s / frame |",
             "|---|---|---|---|---|---|"]
    plt = _plt()
    fig, axes = plt.subplots(1, len(clips), figsize=(5.5 * len(clips), 3.4), squeeze=False)
    for i, (c, label) in enumerate(clips.items()):
        for m in LONG_METHODS:
            r = rows[(c, m)]
            curves = list(r["ori_per_bone_frame"].values())
            per_frame = [sum(v) / len(v) for v in zip(*curves)]
            k = min(125, len(per_frame) // 2)
            first, last = per_frame[:k], per_frame[-k:]
            lines.append(f"| {label} | {NAMES[m]} ({r['seeds']} seeds) | {cell(r)} | "
                         f"{sum(first) / k:.1f} | "
                         f"{sum(last) / k:.1f} | {r['seconds_per_frame']:.2f} |")
            ax = axes[0, i]
            ax.plot([t / 25.0 for t in range(len(per_frame))], per_frame, label=NAMES[m],
                    lw=1)
        axes[0, i].set_title(label, fontsize=9)
        axes[0, i].set_xlabel("time (s)")
        axes[0, i].set_ylabel("validation error (deg)")
        axes[0, i].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(RESULTS / "long.png", dpi=110)
    plt.close(fig)
    return "\n".join(lines)


#: the default tracker with the subject's capsules fitted to the first frame (radii and the
#: head capsule's offset off the neck's axis), to the masks intersected with their visual
#: hull's reprojection, and with the head offset alone (radii kept; outdoors only)
BODY_FIT = [("p_prior_refined", "default tracker (anthropometric capsules)"),
            ("p_prior_refined_fit", "+ radii and head offset fitted (`p_prior_refined_fit`)"),
            ("p_prior_refined_fit_hull", "+ fitted to the hull-filtered masks "
                                         "(`body_fit.hull_filter=true`)"),
            ("p_prior_refined_head", "+ head offset fitted, radii kept")]
STUDIO_FIT = BODY_FIT[:3]
STUDIO = [("demo", "demo walk, CMU 131_01", [0, 1, 2]), ("jog", "HDM05 bd jog", [0]),
          ("sneak", "HDM05 bd sneak", [0]), ("fwalk", "CMU21 female walk", [0])]


def _mean_of(runs: list[dict], key: str) -> float:
    return sum(r[key]["mean"] for r in runs) / len(runs)


def body_fit() -> str:
    """The capsule body fitted to the first frame, outdoors (Fig. 8's runs) and in the studio
    (the default data; runs/studio)."""
    lines = ["# The body model the image term sees: capsules fitted to the first frame's "
             "silhouettes (validation orientation error, deg, mean ± std over frames, bones and "
             "seeds (± spread of the per-seed means); root-aligned MPJPE, mm; silhouette IoU of "
             "the capsules at the first pose before → after the fit; fitted forward offset of "
             "the head capsule, cm)", "",
             "Outdoor (`+experiment=ponsmoll2010/fig8`, tracker seeds 0-2):", "",
             "| activity | " + " | ".join(label for _, label in BODY_FIT) + " |",
             "|---|" + "---|" * len(BODY_FIT)]
    totals: dict[str, list] = {m: [] for m, _ in BODY_FIT}
    for a, label in ACTIVITIES.items():
        cells = []
        for m, _ in BODY_FIT:
            runs = runs_of("fig8", a, m)
            r = combine(runs)
            totals[m].append((r["ori_mean"], _mean_of(runs, "mpjpe_root_relative_mm")))
            extra = ""
            fits = [x["body_fit"] for x in runs if isinstance(x.get("body_fit"), dict)]
            if fits:
                iou0 = sum(f["iou_before"] for f in fits) / len(fits)
                iou1 = sum(f["iou_after"] for f in fits) / len(fits)
                head = [f["offsets"]["head_top"][1] for f in fits if f.get("offsets")]
                extra = f"; IoU {iou0:.2f} → {iou1:.2f}"
                if head:
                    extra += f", head {-100 * sum(head) / len(head):.1f} cm"
            cells.append(f"{cell(r)}; {_mean_of(runs, 'mpjpe_root_relative_mm'):.1f} mm{extra}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("| **all** | " + " | ".join(
        f"**{sum(o for o, _ in v) / len(v):.1f}°; {sum(e for _, e in v) / len(v):.1f} mm**"
        for v in totals.values()) + " |")
    lines += ["", "Studio, the default data (four views of the skinned body, ten IMUs; "
              "`runs/studio`, every frame of each clip):", "",
              "| clip (seeds) | " + " | ".join(label for _, label in STUDIO_FIT) + " |",
              "|---|" + "---|" * len(STUDIO_FIT)]
    for d, label, seeds in STUDIO:
        cells = []
        for m, _ in STUDIO_FIT:
            runs = runs_of("studio", d, m, seeds=seeds)
            cells.append(" / ".join(f"{x['orientation_error_deg']['mean']:.1f}° "
                                    f"({x['mpjpe_root_relative_mm']['mean']:.1f} mm)"
                                    for x in runs))
        lines.append(f"| {label} ({', '.join(map(str, seeds))}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


FIGURES = {"fig8": fig8, "fig9a": fig9a, "fig10": fig10, "control": control,
           "fidelity": fidelity, "long": long, "body_fit": body_fit}
#: figures whose runs lie under another figure's folder
RUN_DIRS = {"body_fit": "fig8"}


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (never a half-written table)."""
    from torchmocap.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("figure", choices=[*FIGURES, "all"])
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    todo = list(FIGURES) if args.figure == "all" else [args.figure]
    for name in todo:
        if args.figure == "all" and not (RUNS / RUN_DIRS.get(name, name)).is_dir():
            print(f"{name}: no runs, skipped", file=sys.stderr)
            continue
        table = FIGURES[name]()
        _write_atomic(RESULTS / f"{name}.md", table + "\n")
        print(table + "\n")


if __name__ == "__main__":
    main()
