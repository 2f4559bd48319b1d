"""Tracker throughput: likelihood evaluations per second and frames per second of method ``p``.

Run:  python experiments/benchmarks/tracker.py [--threads 2] [--frames 12]

1. Silhouette (+ appearance) likelihood throughput: particle-view evaluations per second for
   200 particles x 4 views at 320x240 (the energy of one annealing layer).
2. Tracker ``p`` (Pons-Moll: manifold sampling + vMF, 200 particles x 15 layers, 4 views at
   320x240, silhouettes + appearance) on the bundled CMU walk in the ``studio`` scenario: frames
   per second (target >= 5 on 2 CPU cores), also with the appearance term off.
3. The real bodytrack frame at full resolution (4 views, 640x480): one 200 x 15 annealing pass on
   its silhouettes, beside PARSEC bodytrack's C++ annealed particle filter, which needs 0.086 s
   for 200 particles x 15 layers on one core of this machine class (a number measured outside
   this script: PARSEC is not built here).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path

import torch

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"


def _median(fn, repeats):
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--frames", type=int, default=12)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from torchmocap.body import CapsuleBody
    from torchmocap.data import synthesize
    from torchmocap.data.subject import fit_subject
    from torchmocap.filters.tracker import Tracker, TrackerConfig, frame_observation
    from torchmocap.io import bundled_clip_path, load_motion
    from torchmocap.likelihoods import appearance_energy, body_surface_pattern
    from torchmocap.likelihoods.silhouette import prepare_silhouettes, silhouette_energy

    clip = load_motion(bundled_clip_path()).resample(25).slice(0, args.frames + 1)
    seq = synthesize(fit_subject(clip), "studio", seed=0)
    gt = seq.ground_truth
    sk = gt.build_skeleton().float()
    body = CapsuleBody(sk)
    rig = seq.rig.float()
    f = seq.frame(1)
    obs = prepare_silhouettes(f.silhouettes, 64)
    g = torch.Generator().manual_seed(0)
    theta = gt.theta[1].float() + 0.05 * torch.randn(200, sk.num_dofs, generator=g)
    pattern = body_surface_pattern(body, 3, 4)

    def silh():
        kin = sk(theta, check_finite=False)
        return silhouette_energy(body.endpoints(kin), body.radii, rig, obs)

    def both():
        kin = sk(theta, check_finite=False)
        return (silhouette_energy(body.endpoints(kin), body.radii, rig, obs)
                + appearance_energy(kin, body, pattern, rig, f.images))

    t_s, t_b = _median(silh, 20), _median(both, 20)
    C = rig.num_cameras
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}")
    print("| workload | time | throughput |")
    print("|---|---|---|")
    print(f"| silhouette likelihood, 200 particles x {C} views | {1e3 * t_s:.1f} ms | "
          f"{200 * C / t_s:,.0f} particle-views/s |")
    print(f"| silhouette + appearance, 200 x {C} | {1e3 * t_b:.1f} ms | "
          f"{200 * C / t_b:,.0f} particle-views/s |")

    tracking = seq.imu.tracking.nonzero()[:, 0]
    sensors = {n: b for n, b, t in zip(seq.imu.names, seq.imu.bones,
                                        seq.imu.tracking.tolist()) if t}
    for w_app in (40.0, 0.0):
        tr = Tracker(body, rig, TrackerConfig(method="p", w_app=w_app), sensors=sensors, seed=0)
        st = tr.init(gt.theta[0].float(), frame_observation(seq.frame(0), tracking))
        st, _, _ = tr.step(st, frame_observation(seq.frame(1), tracking))  # warm-up
        t0 = time.perf_counter()
        n = 0
        for t in range(2, seq.num_frames):
            st, _, _ = tr.step(st, frame_observation(seq.frame(t), tracking))
            n += 1
        dt = (time.perf_counter() - t0) / max(n, 1)
        label = "silhouette + appearance" if w_app else "silhouette only"
        print(f"| tracker p, 200 x 15, {C} views 320x240, {label} | {dt:.3f} s/frame | "
              f"{1 / dt:.2f} frames/s (target >= 5) |")

    root = SHARED / "multiview" / "bodytrack_sequenceB_1"
    if root.is_dir():
        from torchmocap.cli.bodytrack import load_bodytrack
        from torchmocap.filters.annealed import anneal, default_diffusion
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
        print(f"| bodytrack frame 640x480 x 4 views, one 200 x 15 anneal | {t_a:.3f} s | "
              f"PARSEC C++ 0.086 s/1 core: ratio {0.086 / t_a:.2f}x |")


if __name__ == "__main__":
    main()
