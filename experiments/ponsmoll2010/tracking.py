"""Pons-Moll et al. (2010) tracking experiments: Fig. 8 (methods x activities), Fig. 9a (error vs
particles) and Fig. 10 (sensor-noise models under misaligned sensors).

Every run: a real motion clip -> subject fit -> observations synthesised from the skinned CC0 body
(not the tracker's capsules) under a scenario -> tracker -> validation error (eq. 19, atan2 form)
of the 5 validation sensors' bones (chest, upper arms, thighs) against ground truth.

    python experiments/ponsmoll2010/tracking.py fig8  [--frames 75] [--particles 200 --layers 15]
    python experiments/ponsmoll2010/tracking.py fig9a [--frames 75]
    python experiments/ponsmoll2010/tracking.py fig10 [--frames 75]
    python experiments/ponsmoll2010/tracking.py control [--frames 75]

Particle methods run with tracker seeds 0, 1, 2 (``--seeds``) on the same observations.

Results (one JSON per run, cached: an interrupted sweep resumes) go to ``results/runs/``; the
tables and plots to ``results/fig8.md|png``, ``fig9a.md|png``, ``fig10.md|png``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
RUNS = RESULTS / "runs"
SHARED = HERE.parents[2] / "shared" / "data" / "mocap"

# activity -> (file, asf, skip_frames, start second)
CLIPS = {
    "walking": ("cmu/131_02.bvh", None, 0, 1.0),
    "jumping": ("cmu/01_01.amc", "cmu/01.asf", 0, 2.0),
    "kicking": ("hdm05/HDM_bd_kickLFront1Reps_001_120.amc", "hdm05/HDM_bd.asf", 0, 0.0),
    "basketball": ("hdm05/HDM_bd_throwBasketball_001_120.amc", "hdm05/HDM_bd.asf", 0, 0.0),
    "dancing": ("cmu/60_12_scaled.bvh", None, 0, 2.0),
    "arm rotation": ("hdm05/HDM_bd_rotateArmsBothBackward1Reps_001_120.amc",
                     "hdm05/HDM_bd.asf", 0, 0.0),
}
METHODS = ["l", "ls", "g", "gs", "rs", "p"]
PAPER_FIG8 = {"p": "10.78 ± 8.5", "gs": "not in Fig. 8", "g": "above P (bar)",
              "rs": "not in Fig. 8", "ls": "above P (bar)", "l": "above P (bar)"}


def load_subject(activity: str, frames: int, fps: float = 25.0):
    from torchmocap.data.subject import fit_subject
    from torchmocap.io import load_motion

    rel, asf, skip, start = CLIPS[activity]
    clip = load_motion(SHARED / rel, asf=SHARED / asf if asf else None, skip_frames=skip)
    clip = clip.resample(fps)
    a = int(round(start * fps))
    clip = clip.slice(a, min(clip.num_frames, a + frames))
    return fit_subject(clip)


def run_one(seq, method: str, seed: int = 0, **overrides) -> dict:
    """Track ``seq`` with ``method``; returns the run's metrics."""
    from torchmocap.body import CapsuleBody
    from torchmocap.filters.tracker import Tracker, TrackerConfig
    from torchmocap.metrics import mpjpe_mm, orientation_error_deg

    gt = seq.ground_truth
    sk = gt.build_skeleton().float()
    body = CapsuleBody(sk)
    names, bones, track = seq.imu.names, seq.imu.bones, seq.imu.tracking.tolist()
    sensors = {n: b for n, b, t in zip(names, bones, track) if t}
    val = [b for b, t in zip(bones, track) if not t]
    diagnose = overrides.pop("diagnose", False)
    cfg = TrackerConfig.preset(method, **overrides)  # conf/tracker/<method>.yaml
    tr = Tracker(body, seq.rig.float(), cfg, sensors=sensors, seed=seed)
    out = tr.run(seq, theta0=gt.theta[0].float(), progress=False)
    extra = {}
    if diagnose:  # is the truth (the fitted pose) a better optimum than what the tracker found?
        from torchmocap.filters.tracker import frame_observation
        from torchmocap.likelihoods.silhouette import prepare_silhouettes

        tk = seq.imu.tracking.nonzero()[:, 0]
        below = []
        for t in range(1, seq.num_frames):
            obs = frame_observation(seq.frame(t), tk)
            prep = prepare_silhouettes(obs["silhouettes"], cfg.fg_samples, blur=0.0,
                                       view_valid=obs.get("view_valid"))
            with torch.no_grad():
                v = tr._image_energy(obs, prep)(torch.stack([gt.theta[t].float(),
                                                             out.theta[t].float()]))
            below.append(bool(v[1] < v[0]))
        extra["estimate_energy_below_truth"] = sum(below) / len(below)
    kin = sk(out.theta)
    vb = [sk.joint_index(b) for b in val]
    ori = orientation_error_deg(kin.rotations[1:, vb], gt.rotations[1:, vb].float())
    mp = mpjpe_mm(kin.positions[1:], gt.positions[1:].float())
    return {"method": method, "seed": seed, **overrides,
            "ori_mean": float(ori.mean()), "ori_std": float(ori.std()),
            "ori_per_frame": ori.mean(1).tolist(),
            "ori_per_bone": {b: float(ori[:, k].mean()) for k, b in enumerate(val)},
            "ori_per_bone_frame": {b: ori[:, k].tolist() for k, b in enumerate(val)},
            "mpjpe_mean": float(mp.mean()), "seconds_per_frame": out.seconds_per_frame,
            "frames": int(out.theta.shape[0]), **extra}


def cached(key: str, fn):
    RUNS.mkdir(parents=True, exist_ok=True)
    path = RUNS / f"{key}.json"
    if path.is_file():
        return json.loads(path.read_text())
    res = fn()
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(res))
    os.replace(tmp, path)
    return res


def combine(runs: list[dict]) -> dict:
    """Pool runs of several tracker seeds: mean error, std over frames x bones x seeds, the spread
    (std) of the per-seed means, per-bone means and per-frame curves averaged over seeds."""
    n = len(runs)
    mean = sum(r["ori_mean"] for r in runs) / n
    std = math.sqrt(sum(r["ori_std"] ** 2 + (r["ori_mean"] - mean) ** 2 for r in runs) / n)
    spread = math.sqrt(sum((r["ori_mean"] - mean) ** 2 for r in runs) / max(n - 1, 1))
    bones = list(runs[0]["ori_per_bone"])
    per_bone = {b: sum(r["ori_per_bone"][b] for r in runs) / n for b in bones}
    per_bone_frame = {b: [sum(v) / n for v in zip(*(r["ori_per_bone_frame"][b] for r in runs))]
                      for b in bones}
    return {"ori_mean": mean, "ori_std": std, "seed_spread": spread, "seeds": n,
            "ori_per_bone": per_bone, "ori_per_bone_frame": per_bone_frame,
            "seconds_per_frame": sum(r["seconds_per_frame"] for r in runs) / n,
            "frames": runs[0]["frames"], "per_seed": [r["ori_mean"] for r in runs]}


def cell(r: dict) -> str:
    """``mean ± std`` of a combined cell (with the seed spread when there are several seeds)."""
    if r.get("seeds", 1) > 1:
        return f"{r['ori_mean']:.1f} ± {r['ori_std']:.1f} (±{r['seed_spread']:.1f})"
    return f"{r['ori_mean']:.1f} ± {r['ori_std']:.1f}"


def synth(activity, frames, scenario, seed=0, **scenario_overrides):
    from torchmocap.data import load_scenario, synthesize

    sc = load_scenario(scenario, **scenario_overrides) if scenario_overrides else scenario
    return synthesize(load_subject(activity, frames), sc, seed=seed)


def fig8(args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = {}
    clips = [a for a in CLIPS if not args.clips or a in args.clips]
    for act in clips:
        seq = None
        for m in METHODS:
            seeds = [0] if m in ("l", "ls") else args.seeds  # L/LS are deterministic
            runs = []
            for seed in seeds:
                key = (f"fig8_{act.replace(' ', '_')}_{m}_{args.particles}x{args.layers}_"
                       f"{args.frames}_s{seed}")

                def go(m=m, act=act, seed=seed):
                    nonlocal seq
                    if seq is None:
                        seq = synth(act, args.frames, "outdoor", seed=0)
                    kw = {} if m in ("l", "ls") else {"num_particles": args.particles,
                                                      "layers": args.layers}
                    if m == "rs":
                        kw["reject_tries"] = args.reject_tries
                    t0 = time.perf_counter()
                    r = run_one(seq, m, seed=seed, **kw)
                    print(f"fig8 {act:>12} {m:>3} seed {seed}: {r['ori_mean']:.2f} deg "
                          f"({time.perf_counter() - t0:.0f} s)", flush=True)
                    return r

                runs.append(cached(key, go))
            rows[(act, m)] = combine(runs)
    if clips != list(CLIPS):
        return  # a partial sweep only fills the cache
    lines = [f"# Fig. 8: validation orientation error (deg): mean ± std over frames, the 5 "
             f"validation sensors and tracker seeds {args.seeds} (± spread of the per-seed "
             f"means); outdoor scenario, up to {args.frames} frames at 25 fps, "
             f"{args.particles} particles x {args.layers} layers (L/LS: deterministic local "
             f"optimisation, one run)",
             "", "| activity | " + " | ".join(m.upper() for m in METHODS) + " |",
             "|---|" + "---|" * len(METHODS)]
    for act in CLIPS:
        cells = [cell(rows[(act, m)]) for m in METHODS]
        lines.append(f"| {act} ({rows[(act, 'p')]['frames'] - 1} frames) | "
                     + " | ".join(cells) + " |")
    allm = {m: [rows[(a, m)] for a in CLIPS] for m in METHODS}
    mean = {m: sum(r["ori_mean"] for r in v) / len(v) for m, v in allm.items()}
    std = {m: math.sqrt(sum(r["ori_std"] ** 2 + (r["ori_mean"] - mean[m]) ** 2 for r in v)
                        / len(v)) for m, v in allm.items()}
    lines.append("| **all** | " + " | ".join(f"**{mean[m]:.1f} ± {std[m]:.1f}**"
                                                for m in METHODS) + " |")
    lines.append("| s / frame | " + " | ".join(
        f"{sum(r['seconds_per_frame'] for r in allm[m]) / len(allm[m]):.2f}" for m in METHODS)
        + " |")
    lines.append("| paper (all) | " + " | ".join(PAPER_FIG8[m] for m in METHODS) + " |")
    (RESULTS / "fig8.md").write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(8, 4))
    w = 0.13
    for k, m in enumerate(METHODS):
        ax.bar([i + (k - 2.5) * w for i in range(len(CLIPS))],
               [rows[(a, m)]["ori_mean"] for a in CLIPS], w, label=m.upper(),
               yerr=[rows[(a, m)]["ori_std"] for a in CLIPS], capsize=2)
    ax.set_xticks(range(len(CLIPS)))
    ax.set_xticklabels(list(CLIPS), fontsize=8)
    ax.set_ylabel("validation error (deg)")
    ax.axhline(10.78, color="k", ls=":", lw=1, label="paper P")
    ax.legend(fontsize=7, ncol=7)
    fig.tight_layout()
    fig.savefig(RESULTS / "fig8.png", dpi=110)
    print("\n".join(lines))


def fig9a(args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    counts = [25, 50, 100, 200]
    res = {}
    seq = None
    for m in ("gs", "p"):
        for n in counts:
            runs = []
            for seed in args.seeds:
                def go(m=m, n=n, seed=seed):
                    nonlocal seq
                    if seq is None:
                        seq = synth("walking", args.frames, "outdoor", seed=0)
                    r = run_one(seq, m, seed=seed, num_particles=n, layers=args.layers)
                    print(f"fig9a {m} {n} seed {seed}: {r['ori_mean']:.2f}", flush=True)
                    return r

                runs.append(cached(f"fig9a_walking_{m}_{n}x{args.layers}_{args.frames}_s{seed}",
                                   go))
            res[(m, n)] = combine(runs)
    lines = ["# Fig. 9a: validation error (deg) vs number of particles, walking clip, outdoor, "
             f"{args.layers} layers, {args.frames} frames, tracker seeds {args.seeds} "
             "(mean ± std over frames, bones and seeds; ± spread of the per-seed means)", "",
             "| particles | " + " | ".join(str(n) for n in counts) + " |",
             "|---|" + "---|" * len(counts)]
    for m in ("gs", "p"):
        lines.append(f"| {m.upper()} | " + " | ".join(cell(res[(m, n)]) for n in counts) + " |")
    (RESULTS / "fig9a.md").write_text("\n".join(lines) + "\n")
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
    print("\n".join(lines))


def fig10(args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    noises = [("none", "none"), ("gaussian", "gaussian"), ("vmf", "vmf")]
    seq = None
    res = {}
    for label, noise in noises:
        runs = []
        for seed in args.seeds:
            def go(noise=noise, seed=seed):
                nonlocal seq
                if seq is None:
                    seq = synth("walking", args.frames, "studio", seed=0,
                                **{"imu.misalignment_deg": [5.0, 10.0]})
                r = run_one(seq, "p", seed=seed, noise=noise, num_particles=args.particles,
                            layers=args.layers)
                print(f"fig10 {noise} seed {seed}: {r['ori_mean']:.2f} (left hip "
                      f"{r['ori_per_bone'].get('l_hip', float('nan')):.2f})", flush=True)
                return r

            runs.append(cached(f"fig10_walking_{noise}_{args.particles}x{args.layers}_"
                               f"{args.frames}_s{seed}", go))
        res[label] = combine(runs)
    paper = {"none": 26.8, "gaussian": 13.0, "vmf": 7.3}
    lines = ["# Fig. 10: left-hip validation error (deg) of P with three sensor-noise models, "
             f"walking clip with 5-10 deg sensor misalignment, {args.particles} x {args.layers}, "
             f"{args.frames} frames, tracker seeds {args.seeds}", "",
             "| noise model | left hip (ours) | all 5 sensors (ours) | left hip (paper) |",
             "|---|---|---|---|"]
    for label, _ in noises:
        r = res[label]
        lines.append(f"| {label} | {r['ori_per_bone']['l_hip']:.1f} | {cell(r)} | "
                     f"{paper[label]} |")
    (RESULTS / "fig10.md").write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for label, _ in noises:
        y = res[label]["ori_per_bone_frame"]["l_hip"]
        ax.plot([(i + 1) / 25 for i in range(len(y))], y, label=label)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("left hip error (deg)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "fig10.png", dpi=110)
    print("\n".join(lines))


def control(args):
    """P on the same clips when the observations come from the tracker's own capsule body
    (clean), from the skinned mesh (clean), and from the skinned mesh outdoors: separates the
    optimiser's share of the error from the body-model mismatch and the image corruption."""
    conditions = [("capsules, clean, fitted truth", "clean",
                   {"body": "capsules", "ground_truth": "fitted"}),
                  ("capsules, clean", "clean", {"body": "capsules"}),
                  ("skinned mesh, clean", "clean", {}),
                  ("skinned mesh, outdoor", "outdoor", {})]
    acts = ["walking", "jumping", "basketball"]
    res = {}
    for label, scen, ov in conditions:
        for act in acts:
            seq = None
            runs = []
            for seed in args.seeds:
                def go(act=act, seed=seed, scen=scen, ov=ov, label=label):
                    nonlocal seq
                    if seq is None:
                        seq = synth(act, args.frames, scen, seed=0, **ov)
                    r = run_one(seq, "p", seed=seed, num_particles=args.particles,
                                layers=args.layers, diagnose=True)
                    print(f"control {label} {act} seed {seed}: {r['ori_mean']:.2f}", flush=True)
                    return r

                tag = label.replace(", ", "_").replace(" ", "-")
                runs.append(cached(f"control_{tag}_{act}_{args.particles}x{args.layers}_"
                                   f"{args.frames}_s{seed}", go))
            c = combine(runs)
            c["below"] = sum(r["estimate_energy_below_truth"] for r in runs) / len(runs)
            res[(label, act)] = c
    lines = ["# Control: P (200 x 15 unless stated) with observations from the tracker's own "
             f"capsules vs the skinned mesh; {args.frames} frames, seeds {args.seeds}. Cells: "
             "validation error (deg) mean ± std (± seed spread); in brackets the fraction of "
             "frames whose estimate has a lower image energy than the true pose.", "",
             "| observations | " + " | ".join(acts) + " |", "|---|" + "---|" * len(acts)]
    for label, _, _ in conditions:
        lines.append(f"| {label} | " + " | ".join(
            f"{cell(res[(label, a)])} [{res[(label, a)]['below']:.2f}]" for a in acts) + " |")
    (RESULTS / "control.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("figure", choices=["fig8", "fig9a", "fig10", "control"])
    ap.add_argument("--frames", type=int, default=75)
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--layers", type=int, default=15)
    ap.add_argument("--reject-tries", type=int, default=50)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="tracker seeds per cell (the observations are the same)")
    ap.add_argument("--clips", nargs="*", default=None,
                    help="fig8: only these activities (fills the cache; the table needs all)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    {"fig8": fig8, "fig9a": fig9a, "fig10": fig10, "control": control}[args.figure](args)


if __name__ == "__main__":
    main()
