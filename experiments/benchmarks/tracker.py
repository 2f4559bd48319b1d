"""Tracker throughput: likelihood evaluations per second and frames per second of preset ``p``.

Run:  python experiments/benchmarks/tracker.py [--threads 2] [--frames 12] [--baseline DIR]

1. Silhouette (+ appearance) likelihood throughput: particle-view evaluations per second for
   200 particles x 4 views at 320x240 (the energy of one annealing layer), through the
   assembled likelihood (:class:`~torchmocap.likelihoods.FrameEnergy`).
2. Tracker ``p`` as built from ``conf/tracker/p.yaml`` (Pons-Moll: manifold sampling + vMF,
   200 particles x 15 layers, 4 views at 320x240, silhouettes + appearance) on the bundled CMU
   walk in the ``studio`` scenario: frames per second (target >= 5 on 2 CPU cores), also with
   the appearance term switched off (``tracker.likelihood.weights.appearance=0``).
3. The real bodytrack frame at full resolution (4 views, 640x480): one 200 x 15 annealing pass on
   its silhouettes, beside PARSEC bodytrack's C++ annealed particle filter, which needs 0.086 s
   for 200 particles x 15 layers on one core of this machine class (a number measured outside
   this script: PARSEC is not built here).

``--baseline DIR`` also runs the same benchmark script of another checkout (e.g. a ``git
worktree`` of an older commit) in a subprocess, alternating with this one ``--rounds`` times, and
prints both tracker rows with their ratio: a before/after measured in one run.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"
ROW = re.compile(r"\| tracker p, .*?, (silhouette[^|]*) \| ([0-9.]+) s/frame")


def _median(fn, repeats):
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def measure(frames: int, bodytrack: bool = True) -> list[str]:
    """The benchmark rows (markdown) of this checkout."""
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data import synthesize
    from torchmocap.data.subject import fit_subject
    from torchmocap.io import bundled_clip_path, load_motion
    from torchmocap.likelihoods import FrameEnergy

    clip = load_motion(bundled_clip_path()).resample(25).slice(0, frames + 1)
    seq = synthesize(fit_subject(clip), "studio", seed=0)
    rt = Runtime.from_sequence(seq)
    sk, rig = rt.skeleton, rt.rig
    tracking = seq.imu.tracking.nonzero()[:, 0]
    g = torch.Generator().manual_seed(0)
    theta = seq.ground_truth.theta[1].float() + 0.05 * torch.randn(200, sk.num_dofs,
                                                                    generator=g)
    rows = []
    C = rig.num_cameras
    image = build_tracker(tracker_config("p"), rt).likelihood
    silh = build_tracker(tracker_config("p", ["tracker.likelihood.weights.appearance=0"]),
                         rt).likelihood
    from torchmocap.filters import Tracker

    frame = Tracker.observe(seq.frame(1), tracking)
    for label, lik in (("silhouette likelihood", silh), ("silhouette + appearance", image)):
        V = FrameEnergy(lik, lik.prepare(frame), sk)
        with torch.no_grad():
            t = _median(lambda V=V: V(theta), 20)
        rows.append(f"| {label}, 200 particles x {C} views | {1e3 * t:.1f} ms | "
                    f"{200 * C / t:,.0f} particle-views/s |")
    for overrides, label in (([], "silhouette + appearance"),
                             (["tracker.likelihood.weights.appearance=0"], "silhouette only")):
        tr = build_tracker(tracker_config("p", overrides), Runtime.from_sequence(seq), seed=0)
        st = tr.init(seq.ground_truth.theta[0].float(), tr.observe(seq.frame(0), tracking))
        st, _, _ = tr.step(st, tr.observe(seq.frame(1), tracking))  # warm-up
        t0 = time.perf_counter()
        n = 0
        for t in range(2, seq.num_frames):
            st, _, _ = tr.step(st, tr.observe(seq.frame(t), tracking))
            n += 1
        dt = (time.perf_counter() - t0) / max(n, 1)
        rows.append(f"| tracker p, 200 x 15, {C} views 320x240, {label} | {dt:.3f} s/frame | "
                    f"{1 / dt:.2f} frames/s (target >= 5) |")

    root = SHARED / "multiview" / "bodytrack_sequenceB_1"
    if bodytrack and root.is_dir():
        from torchmocap.body import CapsuleBody
        from torchmocap.data.bodytrack import load_bodytrack
        from torchmocap.filters.annealed import anneal, default_diffusion
        from torchmocap.likelihoods.silhouette import prepare_silhouettes, silhouette_energy
        from torchmocap.skeleton import human31

        brig, _, masks = load_bodytrack(root)
        brig = brig.float()
        bsk = human31()
        bbody = CapsuleBody(bsk)
        bobs = prepare_silhouettes(masks, 64)
        x0 = bsk.zero_pose() + 0.05 * torch.randn(200, bsk.num_dofs, generator=g)
        x0[:, 0] += 0.15
        x0[:, 1] += 0.9

        def energy(th):
            return silhouette_energy(bbody.endpoints(bsk(th, check_finite=False)), bbody.radii,
                                     brig, bobs)

        def one_pass():
            anneal(energy, x0, layers=15, diffusion=default_diffusion(15),
                   lower=bsk.lower, upper=bsk.upper, generator=torch.Generator().manual_seed(1))

        t_a = _median(one_pass, 5)
        rows.append(f"| bodytrack frame 640x480 x 4 views, one 200 x 15 anneal | {t_a:.3f} s | "
                    f"PARSEC C++ 0.086 s/1 core: ratio {0.086 / t_a:.2f}x |")
    return rows


def _baseline_rows(path: Path, threads: int, frames: int) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(path), OMP_NUM_THREADS=str(threads))
    script = path / "experiments" / "benchmarks" / "tracker.py"
    r = subprocess.run([sys.executable, str(script), "--threads", str(threads), "--frames",
                        str(frames), "--no-bodytrack"], capture_output=True, text=True, env=env,
                       cwd=path)
    if r.returncode != 0:  # older scripts have no --no-bodytrack
        r = subprocess.run([sys.executable, str(script), "--threads", str(threads), "--frames",
                            str(frames)], capture_output=True, text=True, env=env, cwd=path)
    if r.returncode != 0:
        raise SystemExit(f"baseline {script} failed:\n{r.stderr[-2000:]}")
    return {m.group(1).strip(): float(m.group(2)) for m in ROW.finditer(r.stdout)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--baseline", type=Path, default=None,
                    help="another checkout to time in the same run (before/after)")
    ap.add_argument("--rounds", type=int, default=3, help="alternations with --baseline")
    ap.add_argument("--no-bodytrack", action="store_true", help="skip the real-frame row")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}")
    if args.baseline is None:
        print("| workload | time | throughput |")
        print("|---|---|---|")
        print("\n".join(measure(args.frames, not args.no_bodytrack)))
        return
    ours: dict[str, list[float]] = {}
    base: dict[str, list[float]] = {}
    for _ in range(args.rounds):
        for k, v in _baseline_rows(args.baseline.resolve(), args.threads, args.frames).items():
            base.setdefault(k, []).append(v)
        for row in measure(args.frames, bodytrack=False):
            m = ROW.search(row)
            if m:
                ours.setdefault(m.group(1).strip(), []).append(float(m.group(2)))
    print(f"| tracker p, 200 x 15 | baseline {args.baseline.name} s/frame (median of "
          f"{args.rounds}) | this checkout s/frame | speed ratio (baseline / this) |")
    print("|---|---|---|---|")
    for k in ours:
        if k in base:
            b, o = statistics.median(base[k]), statistics.median(ours[k])
            print(f"| {k} | {b:.3f} ({', '.join(f'{x:.3f}' for x in base[k])}) | {o:.3f} "
                  f"({', '.join(f'{x:.3f}' for x in ours[k])}) | {b / o:.2f}x |")


if __name__ == "__main__":
    main()
