"""Pons-Moll et al. (2010) tracking experiments: Fig. 8 (methods x activities), Fig. 9a (error vs
particles) and Fig. 10 (sensor-noise models under misaligned sensors).

Every run: a real motion clip -> subject fit -> observations synthesised from the skinned CC0 body
(not the tracker's capsules) under a scenario -> tracker -> validation error (eq. 19, atan2 form)
of the 5 validation sensors' bones (chest, upper arms, thighs) against ground truth.

    python experiments/ponsmoll2010/tracking.py fig8  [--frames 40] [--particles 100 --layers 10]
    python experiments/ponsmoll2010/tracking.py fig9a [--frames 40]
    python experiments/ponsmoll2010/tracking.py fig10 [--frames 60]

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
    "kicking": ("hdm05/HDM_bd_kickLFront1Reps_001_120.amc", "hdm05/HDM_bd.asf", 0, 0.5),
    "basketball": ("hdm05/HDM_bd_throwBasketball_001_120.amc", "hdm05/HDM_bd.asf", 0, 0.5),
    "dancing": ("cmu/60_12_scaled.bvh", None, 0, 2.0),
    "arm rotation": ("hdm05/HDM_bd_rotateArmsBothBackward1Reps_001_120.amc",
                     "hdm05/HDM_bd.asf", 0, 0.5),
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
    cfg = TrackerConfig(method=method, **overrides)
    tr = Tracker(body, seq.rig.float(), cfg, sensors=sensors, seed=seed)
    out = tr.run(seq, theta0=gt.theta[0].float(), progress=False)
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
            "frames": int(out.theta.shape[0])}


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


def synth(activity, frames, scenario, seed=0, **scenario_overrides):
    from torchmocap.data import load_scenario, synthesize

    sc = load_scenario(scenario, **scenario_overrides) if scenario_overrides else scenario
    return synthesize(load_subject(activity, frames), sc, seed=seed)


def fig8(args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = {}
    for act in CLIPS:
        seq = None
        for m in METHODS:
            key = f"fig8_{act.replace(' ', '_')}_{m}_{args.particles}x{args.layers}_{args.frames}"

            def go(m=m, act=act):
                nonlocal seq
                if seq is None:
                    seq = synth(act, args.frames, "outdoor", seed=0)
                kw = {} if m in ("l", "ls") else {"num_particles": args.particles,
                                                  "layers": args.layers}
                if m == "rs":
                    kw["reject_tries"] = args.reject_tries
                t0 = time.perf_counter()
                r = run_one(seq, m, **kw)
                print(f"fig8 {act:>12} {m:>3}: {r['ori_mean']:.2f} deg "
                      f"({time.perf_counter() - t0:.0f} s)", flush=True)
                return r

            rows[(act, m)] = cached(key, go)
    lines = [f"# Fig. 8: validation orientation error (deg, mean ± std over frames and the 5 "
             f"validation sensors), outdoor scenario, {args.frames} frames at 25 fps, "
             f"{args.particles} particles x {args.layers} layers (L/LS: local optimisation)",
             "", "| activity | " + " | ".join(m.upper() for m in METHODS) + " |",
             "|---|" + "---|" * len(METHODS)]
    for act in CLIPS:
        cells = [f"{rows[(act, m)]['ori_mean']:.1f} ± {rows[(act, m)]['ori_std']:.1f}"
                 for m in METHODS]
        lines.append(f"| {act} | " + " | ".join(cells) + " |")
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
            def go(m=m, n=n):
                nonlocal seq
                if seq is None:
                    seq = synth("walking", args.frames, "outdoor", seed=0)
                r = run_one(seq, m, num_particles=n, layers=args.layers)
                print(f"fig9a {m} {n}: {r['ori_mean']:.2f}", flush=True)
                return r

            res[(m, n)] = cached(f"fig9a_walking_{m}_{n}x{args.layers}_{args.frames}", go)
    lines = ["# Fig. 9a: validation error (deg) vs number of particles, walking clip, outdoor, "
             f"{args.layers} layers, {args.frames} frames", "",
             "| particles | " + " | ".join(str(n) for n in counts) + " |",
             "|---|" + "---|" * len(counts)]
    for m in ("gs", "p"):
        lines.append(f"| {m.upper()} | " + " | ".join(
            f"{res[(m, n)]['ori_mean']:.1f} ± {res[(m, n)]['ori_std']:.1f}" for n in counts)
            + " |")
    (RESULTS / "fig9a.md").write_text("\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for m in ("gs", "p"):
        ax.errorbar(counts, [res[(m, n)]["ori_mean"] for n in counts],
                    [res[(m, n)]["ori_std"] for n in counts], marker="o", capsize=3,
                    label=m.upper())
    ax.set_xscale("log")
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
        def go(noise=noise):
            nonlocal seq
            if seq is None:
                seq = synth("walking", args.frames, "studio", seed=0,
                            **{"imu.misalignment_deg": [5.0, 10.0]})
            r = run_one(seq, "p", noise=noise, num_particles=args.particles, layers=args.layers)
            print(f"fig10 {noise}: {r['ori_mean']:.2f} (left hip "
                  f"{r['ori_per_bone'].get('l_hip', float('nan')):.2f})", flush=True)
            return r

        res[label] = cached(f"fig10_walking_{noise}_{args.particles}x{args.layers}_"
                            f"{args.frames}", go)
    paper = {"none": 26.8, "gaussian": 13.0, "vmf": 7.3}
    lines = ["# Fig. 10: left-hip validation error (deg) of P with three sensor-noise models, "
             f"walking clip with 5-10 deg sensor misalignment, {args.particles} x {args.layers}, "
             f"{args.frames} frames", "",
             "| noise model | left hip (ours) | all 5 sensors (ours) | left hip (paper) |",
             "|---|---|---|---|"]
    for label, _ in noises:
        r = res[label]
        lines.append(f"| {label} | {r['ori_per_bone']['l_hip']:.1f} | {r['ori_mean']:.1f} ± "
                     f"{r['ori_std']:.1f} | {paper[label]} |")
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


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("figure", choices=["fig8", "fig9a", "fig10"])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--layers", type=int, default=10)
    ap.add_argument("--reject-tries", type=int, default=50)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    {"fig8": fig8, "fig9a": fig9a, "fig10": fig10}[args.figure](args)


if __name__ == "__main__":
    main()
