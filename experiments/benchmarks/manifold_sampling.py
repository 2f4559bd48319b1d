"""Benchmark: manifold sampling (Pons-Moll et al. §4) per frame, human31 + 5 sensors, float32.

One "frame" = ``ManifoldProposal.sample``: diffuse the 16 active coordinates of P particles,
draw per-particle sensor noise (none / Gaussian on passive parameters / vMF kappa=1000 /
tangent Gaussian), and map every particle to a full 31-DoF pose with the analytic g^{-1}
(likelihood excluded, as in the paper's Fig. 9b). Also times the g^{-1} core alone and the
general Paden–Kahan solver against the closed-form orthogonal one.

Run (one thread, the setting of REFERENCE.md's timings):

    OMP_NUM_THREADS=1 python experiments/benchmarks/manifold_sampling.py [--profile]

Prints a markdown table (wall-clock best of repeats, and CPU time; the last rows use the opt-in
``torch.compile`` of the g^{-1} core, compiled once per input signature before timing) and, with
--profile, the top operators from torch.profiler for 200 particles with vMF noise.
"""

from __future__ import annotations

import argparse
import time

import torch

from torchmocap.geometry.subproblems import three_axis_decomposition
from torchmocap.ik import SensorManifold
from torchmocap.proposals import (
    ManifoldProposal,
    NoSensorNoise,
    PassiveGaussianNoise,
    ProposalContext,
    TangentGaussianNoise,
    VonMisesFisherNoise,
)
from torchmocap.skeleton import human31

NOISES = {"none": NoSensorNoise, "gaussian": PassiveGaussianNoise, "vmf": VonMisesFisherNoise,
          "tangent_gaussian": TangentGaussianNoise}


def best_time(fn, repeats: int = 15, inner: int = 10) -> tuple[float, float]:
    """(best wall-clock, best CPU) seconds per call over ``repeats`` blocks of ``inner`` calls."""
    for _ in range(3):
        fn()
    wall = cpu = float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(inner):
            fn()
        wall = min(wall, (time.perf_counter() - t0) / inner)
        cpu = min(cpu, (time.process_time() - c0) / inner)
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", action="store_true", help="print torch.profiler top ops")
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    torch.set_num_threads(1)
    sk = human31()
    m = SensorManifold(sk)
    g = torch.Generator().manual_seed(0)
    theta0 = torch.zeros(sk.num_dofs)
    theta0[sk.joint_dofs("l_elbow")] = 0.5
    theta0[sk.joint_dofs("r_knee")] = 0.3
    sensors = m.sensor_orientations(theta0)
    ctx = ProposalContext(previous=theta0, sensors=sensors)
    rows = []
    print("| particles | noise | residuals | ms / frame (wall, best) | ms (CPU) |")
    print("|---:|---|---|---:|---:|")
    for P in (200, 3000):
        for noise in NOISES:
            for res in (False, True):
                prop = ManifoldProposal(m, active_std=0.05, noise=NOISES[noise](),
                                        compute_residual=res)
                w, c = best_time(lambda prop=prop, P=P: prop.sample(ctx, P, g), args.repeats)
                rows.append((P, noise, res, w, c))
                print(f"| {P} | {noise} | {'yes' if res else 'no'} | {w * 1e3:.3f} | "
                      f"{c * 1e3:.3f} |", flush=True)
    # opt-in torch.compile of the g^{-1} core (a separate manifold, compiled once per shape)
    mc = SensorManifold(sk).compile_inverse()
    t0 = time.perf_counter()
    for P in (200, 3000):
        for noise in ("none", "vmf"):
            prop = ManifoldProposal(mc, active_std=0.05, noise=NOISES[noise](),
                                    compute_residual=False)
            w, c = best_time(lambda prop=prop, P=P: prop.sample(ctx, P, g), args.repeats)
            print(f"| {P} | {noise}, compiled g^-1 | no | {w * 1e3:.3f} | {c * 1e3:.3f} |",
                  flush=True)
    print(f"(compilation and runs: {time.perf_counter() - t0:.0f} s)")
    # g^{-1} core alone and the 3-axis solvers
    print()
    print("| part | N | ms (wall, best) |")
    print("|---|---:|---:|")
    for P in (200, 3000):
        xa = m(theta0.expand(P, -1))
        w, _ = best_time(lambda xa=xa: m.inverse(xa, sensors, compute_residual=False,
                                                 validate=False), args.repeats)
        print(f"| g^-1 (5 sensors, closed form) | {P} particles | {w * 1e3:.3f} |")
        R = torch.eye(3).expand(P, 3, 3).contiguous()
        ax = torch.eye(3)
        w, _ = best_time(lambda R=R, ax=ax: three_axis_decomposition(R, ax[2], ax[1], ax[0],
                                                              compute_residual=False),
                         args.repeats)
        print(f"| general 3-axis Paden–Kahan | {P} joints | {w * 1e3:.3f} |")
    if args.profile:
        from torch.profiler import profile

        prop = ManifoldProposal(m, active_std=0.05, noise=VonMisesFisherNoise(),
                                compute_residual=False)
        for _ in range(5):
            prop.sample(ctx, 200, g)
        with profile() as prof:
            for _ in range(50):
                prop.sample(ctx, 200, g)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20))


if __name__ == "__main__":
    main()
