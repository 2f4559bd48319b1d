"""Tables and plots of the learned-likelihood evaluation from the runs' metrics.json files.

    python experiments/learned_likelihood/summarize.py

Reads ``runs/<tracker>_<handcrafted|learned>/seed<k>/<job>/metrics.json`` (written by
``run_eval.sh``), writes ``results.md`` and ``errors.png`` beside this file.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: run-directory suffix -> label; the first is the reference of the change columns
ARMS = {"handcrafted": "hand-crafted", "learned": "learned (2 V_silh + learned, bundled)",
        "learnedimage": "learned variant B (image + learned)",
        "distance": "hand-crafted, distance silhouette term (the current preset)"}
def load() -> dict:
    rows = defaultdict(list)  # (tracker, likelihood, clip) -> [(seed, ori, mpjpe, spf)]
    for p in sorted((HERE / "runs").rglob("metrics.json")):
        top = p.relative_to(HERE / "runs").parts[0]  # <tracker>_<arm>
        arm = top.rsplit("_", 1)[-1]
        if arm not in ARMS:
            continue
        m = json.loads(p.read_text())
        lik = ARMS[arm]
        key = (m["tracker"], lik, m["clip"].get("name"))
        rows[key].append((m["seed"], m["orientation_error_deg"]["mean"], m["mpjpe_mm"]["mean"],
                          m["seconds_per_frame"]))
    return rows


def _ms(v: list[float]) -> tuple[float, float]:
    n = len(v)
    mu = sum(v) / n
    sd = math.sqrt(sum((x - mu) ** 2 for x in v) / (n - 1)) if n > 1 else 0.0
    return mu, sd


def main() -> None:
    rows = load()
    trackers = sorted({k[0] for k in rows})
    clips = sorted({k[2] for k in rows})
    out = ["# Learned vs hand-crafted likelihood (held-out subjects, outdoor scenario)", "",
           "Mean over frames 1..T-1 of each run; ± is the standard deviation over seeds (each "
           "seed synthesises its own observations and drives its own tracker).", ""]
    out += ["| tracker | clip | likelihood | seeds | orientation error (deg) | MPJPE (mm) | "
            "s / frame |", "|---|---|---|---|---|---|---|"]
    summary = {}
    for t in trackers:
        for lik in ARMS.values():
            allo, allm, alls = [], [], []
            for c in clips:
                r = rows.get((t, lik, c))
                if not r:
                    continue
                o, mp, s = _ms([x[1] for x in r]), _ms([x[2] for x in r]), _ms([x[3] for x in r])
                out.append(f"| {t} | {c} | {lik} | {len(r)} | {o[0]:.1f} ± {o[1]:.1f} | "
                           f"{mp[0]:.0f} ± {mp[1]:.0f} | {s[0]:.2f} |")
                allo += [x[1] for x in r]
                allm += [x[2] for x in r]
                alls += [x[3] for x in r]
            if allo:
                # per-seed means over clips, for the spread of the overall mean
                seeds = defaultdict(list)
                for c in clips:
                    for x in rows.get((t, lik, c), []):
                        seeds[x[0]].append(x[1])
                per_seed = [sum(v) / len(v) for v in seeds.values()]
                summary[(t, lik)] = (_ms(allo)[0], _ms(per_seed)[1], _ms(allm)[0],
                                     _ms(alls)[0], len(seeds))
    out += ["", "## All clips", "",
            "| tracker | likelihood | orientation error (deg) | ± over seeds | MPJPE (mm) | "
            "s / frame | change in orientation error | time ratio |",
            "|---|---|---|---|---|---|---|---|"]
    for t in trackers:
        base = summary.get((t, "hand-crafted"))
        for lik in ARMS.values():
            s = summary.get((t, lik))
            if s is None:
                continue
            ch = tr = ""
            if base is not None and lik != "hand-crafted":
                ch = f"{100 * (s[0] - base[0]) / base[0]:+.1f} %"
                tr = f"{s[3] / base[3]:.2f}x"
            out.append(f"| {t} | {lik} | {s[0]:.1f} | {s[1]:.1f} | {s[2]:.0f} | {s[3]:.2f} | "
                       f"{ch} | {tr} |")
    (HERE / "results.md").write_text("\n".join(out) + "\n")
    print("\n".join(out))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(1, len(trackers), figsize=(4.5 * len(trackers), 3.6), squeeze=False)
    for i, t in enumerate(trackers):
        a = ax[0, i]
        arms = [lk for lk in ARMS.values() if any((t, lk, c) in rows for c in clips)]
        w = 0.8 / len(arms)
        for j, lik in enumerate(arms):
            mus, sds = [], []
            for c in clips:
                r = rows.get((t, lik, c), [])
                mu, sd = _ms([x[1] for x in r]) if r else (math.nan, 0.0)
                mus.append(mu)
                sds.append(sd)
            xs = [k + (j - (len(arms) - 1) / 2) * w for k in range(len(clips))]
            a.bar(xs, mus, w, yerr=sds, label=lik, capsize=3)
        a.set_xticks(range(len(clips)), clips, rotation=20)
        a.set_title(f"tracker {t}")
        a.set_ylabel("validation orientation error (deg)")
        a.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(HERE / "errors.png", dpi=110)


if __name__ == "__main__":
    main()
